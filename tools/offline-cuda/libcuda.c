/*
 * A CUDA driver that compiles but never runs: the entry points cudarc and cubecl-cuda call,
 * for one "H100" that accepts every module and launch and executes nothing.
 *
 * Why: with it, `f3g --device cuda` runs on a machine without a GPU, and everything before the
 * GPU is real: Burn and CubeCL choose and expand every kernel a step launches with an H100's
 * properties, NVRTC compiles each one (the real library, from PyPI), autotune compiles its
 * candidates, the compilation cache fills. `tools/cuda-offline.sh` builds it and runs
 * `f3g bench train --device cuda` against it to count and time those compilations.
 *
 * What it cannot tell: anything about results. Kernels do not run, so device memory is never
 * written; allocations are addresses only, and every copy to the host reads zeros (the splat
 * op's intersection count is 0, so its raster kernels are not reached: those are compiled by
 * crates/splat/tests/cuda_kernels.rs). Launches are checked against the device's limits
 * (block size, grid, shared memory) and refused with CUDA_ERROR_INVALID_VALUE beyond them, as
 * the real driver would. Event timings are 0 ms, so autotune keeps its first candidate.
 *
 * Types follow cuda.h (CUDA 13.0); attribute numbers are CUdevice_attribute's.
 */
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

typedef int CUresult;
typedef int CUdevice;
typedef unsigned long long CUdeviceptr;
typedef void *CUcontext, *CUstream, *CUevent, *CUmodule, *CUfunction;

enum { SUCCESS = 0, INVALID_VALUE = 1, INVALID_DEVICE = 101, NOT_SUPPORTED = 801 };

/* F3G_OFFLINE_TRACE=FILE: appends one line per launch (`L kernel gx gy gz`), synchronisation
 * (`S ctx|stream|event`) and copy to the host (`R bytes`), in the order the process made them,
 * unbuffered: `f3g bench train` with F3G_PHASE_TRACE=FILE appends its phase marks to the same
 * file, and tools/phase_profile.py places each launch of a GPU's kernel profile in its phase. */
static FILE *trace_file(void) {
    static FILE *file;
    static int opened;
    if (!__atomic_load_n(&opened, __ATOMIC_ACQUIRE)) {
        const char *path = getenv("F3G_OFFLINE_TRACE");
        FILE *f = path && *path ? fopen(path, "a") : NULL;
        if (f) setvbuf(f, NULL, _IONBF, 0);
        if (!__sync_bool_compare_and_swap(&file, NULL, f) && f) fclose(f);
        __atomic_store_n(&opened, 1, __ATOMIC_RELEASE);
    }
    return file;
}
__attribute__((format(printf, 1, 2))) static void trace(const char *format, ...) {
    FILE *f = trace_file();
    if (!f) return;
    va_list args;
    va_start(args, format);
    vfprintf(f, format, args);
    va_end(args);
}

static const size_t TOTAL_MEMORY = 80ull << 30;
static const int MAX_SHARED_OPTIN = 232448;

static int check_device(CUdevice d) { return d == 0 ? SUCCESS : INVALID_DEVICE; }

CUresult cuInit(unsigned flags) { (void)flags; return SUCCESS; }
CUresult cuDriverGetVersion(int *version) { *version = 13000; return SUCCESS; }
CUresult cuDeviceGetCount(int *count) { *count = 1; return SUCCESS; }
CUresult cuDeviceGet(CUdevice *device, int ordinal) {
    if (ordinal != 0) return INVALID_DEVICE;
    *device = 0;
    return SUCCESS;
}
CUresult cuDeviceGetName(char *name, int len, CUdevice d) {
    snprintf(name, (size_t)len, "NVIDIA H100 (offline: compiles, never runs)");
    return check_device(d);
}
CUresult cuDeviceTotalMem_v2(size_t *bytes, CUdevice d) { *bytes = TOTAL_MEMORY; return check_device(d); }
CUresult cuDeviceGetPCIBusId(char *id, int len, CUdevice d) {
    snprintf(id, (size_t)len, "0000:00:00.0");
    return check_device(d);
}
CUresult cuDeviceGetUuid(unsigned char *uuid, CUdevice d) { memset(uuid, 0, 16); return check_device(d); }
CUresult cuDeviceGetUuid_v2(unsigned char *uuid, CUdevice d) { return cuDeviceGetUuid(uuid, d); }

CUresult cuDeviceGetAttribute(int *value, int attribute, CUdevice d) {
    switch (attribute) {
    case 1: *value = 1024; break;                  /* max threads per block */
    case 2: case 3: *value = 1024; break;          /* max block dim x, y */
    case 4: *value = 64; break;                    /* max block dim z */
    case 5: *value = 2147483647; break;            /* max grid dim x */
    case 6: case 7: *value = 65535; break;         /* max grid dim y, z */
    case 8: *value = 49152; break;                 /* shared memory per block */
    case 9: *value = 65536; break;                 /* constant memory */
    case 10: *value = 32; break;                   /* warp size */
    case 12: *value = 65536; break;                /* registers per block */
    case 13: *value = 1980000; break;              /* clock rate, kHz */
    case 16: *value = 132; break;                  /* multiprocessors */
    case 33: case 34: case 50: *value = 0; break;  /* PCI bus, device, domain */
    case 36: *value = 2619000; break;              /* memory clock, kHz */
    case 37: *value = 5120; break;                 /* memory bus width */
    case 38: *value = 50 << 20; break;             /* L2 cache */
    case 39: *value = 2048; break;                 /* threads per multiprocessor */
    case 75: *value = 9; break;                    /* compute capability major */
    case 76: *value = 0; break;                    /* minor */
    case 81: *value = 233472; break;               /* shared memory per multiprocessor */
    case 82: *value = 65536; break;                /* registers per multiprocessor */
    case 97: *value = MAX_SHARED_OPTIN; break;     /* shared memory per block, opt-in */
    default: *value = 1; break;                    /* the capability flags: supported */
    }
    return check_device(d);
}

static int context;
CUresult cuDevicePrimaryCtxRetain(CUcontext *ctx, CUdevice d) { *ctx = &context; return check_device(d); }
CUresult cuDevicePrimaryCtxRelease_v2(CUdevice d) { return check_device(d); }
CUresult cuCtxSetCurrent(CUcontext ctx) { (void)ctx; return SUCCESS; }
CUresult cuCtxGetCurrent(CUcontext *ctx) { *ctx = &context; return SUCCESS; }
CUresult cuCtxGetDevice(CUdevice *d) { *d = 0; return SUCCESS; }
CUresult cuCtxSynchronize(void) { trace("S ctx\n"); return SUCCESS; }
CUresult cuCtxGetStreamPriorityRange(int *least, int *greatest) { *least = 0; *greatest = -5; return SUCCESS; }

/* Streams and events are distinct non-null handles; nothing is ever pending. */
static CUstream new_handle(void) { return malloc(1); }
CUresult cuStreamCreate(CUstream *s, unsigned flags) { (void)flags; *s = new_handle(); return SUCCESS; }
CUresult cuStreamCreateWithPriority(CUstream *s, unsigned flags, int priority) {
    (void)priority;
    return cuStreamCreate(s, flags);
}
CUresult cuStreamDestroy_v2(CUstream s) { free(s); return SUCCESS; }
CUresult cuStreamSynchronize(CUstream s) { (void)s; trace("S stream\n"); return SUCCESS; }
CUresult cuStreamQuery(CUstream s) { (void)s; return SUCCESS; }
CUresult cuStreamWaitEvent(CUstream s, CUevent e, unsigned flags) { (void)s; (void)e; (void)flags; return SUCCESS; }
CUresult cuEventCreate(CUevent *e, unsigned flags) { (void)flags; *e = new_handle(); return SUCCESS; }
CUresult cuEventDestroy_v2(CUevent e) { free(e); return SUCCESS; }
CUresult cuEventRecord(CUevent e, CUstream s) { (void)e; (void)s; return SUCCESS; }
CUresult cuEventRecordWithFlags(CUevent e, CUstream s, unsigned flags) { (void)e; (void)s; (void)flags; return SUCCESS; }
CUresult cuEventSynchronize(CUevent e) { (void)e; trace("S event\n"); return SUCCESS; }
CUresult cuEventQuery(CUevent e) { (void)e; return SUCCESS; }
CUresult cuEventElapsedTime_v2(float *ms, CUevent start, CUevent end) {
    (void)start; (void)end;
    *ms = 0.0f;
    return SUCCESS;
}
CUresult cuEventElapsedTime(float *ms, CUevent start, CUevent end) { return cuEventElapsedTime_v2(ms, start, end); }

/* Device memory: addresses only, 256-byte aligned, never reused, never backed. */
static CUdeviceptr next_address = 1ull << 40;
static size_t allocated;
static CUresult allocate(CUdeviceptr *p, size_t bytes) {
    if (bytes > TOTAL_MEMORY) return 2; /* CUDA_ERROR_OUT_OF_MEMORY */
    *p = __atomic_fetch_add(&next_address, (bytes + 255) / 256 * 256 + 256, __ATOMIC_RELAXED);
    __atomic_fetch_add(&allocated, bytes, __ATOMIC_RELAXED);
    return SUCCESS;
}
CUresult cuMemAlloc_v2(CUdeviceptr *p, size_t bytes) { return allocate(p, bytes); }
CUresult cuMemAllocAsync(CUdeviceptr *p, size_t bytes, CUstream s) { (void)s; return allocate(p, bytes); }
CUresult cuMemFree_v2(CUdeviceptr p) { (void)p; return SUCCESS; }
CUresult cuMemFreeAsync(CUdeviceptr p, CUstream s) { (void)p; (void)s; return SUCCESS; }
CUresult cuMemGetInfo_v2(size_t *free_bytes, size_t *total) {
    *total = TOTAL_MEMORY;
    *free_bytes = TOTAL_MEMORY;
    return SUCCESS;
}
/* Pinned host memory is real: the host writes into it before a copy. */
CUresult cuMemAllocHost_v2(void **p, size_t bytes) { *p = calloc(1, bytes ? bytes : 1); return *p ? SUCCESS : 2; }
CUresult cuMemHostAlloc(void **p, size_t bytes, unsigned flags) { (void)flags; return cuMemAllocHost_v2(p, bytes); }
CUresult cuMemFreeHost(void *p) { free(p); return SUCCESS; }

/* Copies to the device go nowhere; copies to the host read zeros. */
CUresult cuMemcpyHtoDAsync_v2(CUdeviceptr dst, const void *src, size_t n, CUstream s) { (void)dst; (void)src; (void)n; (void)s; return SUCCESS; }
CUresult cuMemcpyHtoD_v2(CUdeviceptr dst, const void *src, size_t n) { (void)dst; (void)src; (void)n; return SUCCESS; }
CUresult cuMemcpyDtoHAsync_v2(void *dst, CUdeviceptr src, size_t n, CUstream s) { (void)src; (void)s; memset(dst, 0, n); trace("R %zu\n", n); return SUCCESS; }
CUresult cuMemcpyDtoH_v2(void *dst, CUdeviceptr src, size_t n) { (void)src; memset(dst, 0, n); trace("R %zu\n", n); return SUCCESS; }
CUresult cuMemcpyDtoDAsync_v2(CUdeviceptr dst, CUdeviceptr src, size_t n, CUstream s) { (void)dst; (void)src; (void)n; (void)s; return SUCCESS; }
CUresult cuMemsetD8Async(CUdeviceptr dst, unsigned char v, size_t n, CUstream s) { (void)dst; (void)v; (void)n; (void)s; return SUCCESS; }
CUresult cuMemsetD32Async(CUdeviceptr dst, unsigned v, size_t n, CUstream s) { (void)dst; (void)v; (void)n; (void)s; return SUCCESS; }

typedef struct {
    size_t srcXInBytes, srcY;
    int srcMemoryType;
    const void *srcHost;
    CUdeviceptr srcDevice;
    void *srcArray;
    size_t srcPitch;
    size_t dstXInBytes, dstY;
    int dstMemoryType;
    void *dstHost;
    CUdeviceptr dstDevice;
    void *dstArray;
    size_t dstPitch;
    size_t WidthInBytes, Height;
} CUDA_MEMCPY2D;
CUresult cuMemcpy2DAsync_v2(const CUDA_MEMCPY2D *c, CUstream s) {
    (void)s;
    if (c->dstMemoryType == 1 /* host */) {
        trace("R %zu\n", c->WidthInBytes * c->Height);
        for (size_t row = 0; row < c->Height; row++)
            memset((char *)c->dstHost + (c->dstY + row) * c->dstPitch + c->dstXInBytes, 0, c->WidthInBytes);
    }
    return SUCCESS;
}

/* Modules: PTX is accepted as it is (the real driver would JIT it to SASS). */
static size_t modules, launches;
CUresult cuModuleLoadData(CUmodule *m, const void *image) { (void)image; __atomic_fetch_add(&modules, 1, __ATOMIC_RELAXED); *m = new_handle(); return SUCCESS; }
CUresult cuModuleLoadDataEx(CUmodule *m, const void *image, unsigned n, int *options, void **values) {
    (void)n; (void)options; (void)values;
    return cuModuleLoadData(m, image);
}
CUresult cuModuleUnload(CUmodule m) { free(m); return SUCCESS; }
/* A function's handle is its name (for the trace): distinct and non-null, as the real ones. */
CUresult cuModuleGetFunction(CUfunction *f, CUmodule m, const char *name) {
    (void)m;
    *f = strdup(name);
    return *f ? SUCCESS : 2;
}
CUresult cuFuncSetAttribute(CUfunction f, int attribute, int value) {
    (void)f;
    /* CU_FUNC_ATTRIBUTE_MAX_DYNAMIC_SHARED_SIZE_BYTES */
    if (attribute == 8 && value > MAX_SHARED_OPTIN) return INVALID_VALUE;
    return SUCCESS;
}
CUresult cuFuncGetAttribute(int *value, int attribute, CUfunction f) {
    (void)f;
    *value = attribute == 0 ? 1024 : 0; /* max threads per block; sizes and registers 0 */
    return SUCCESS;
}

CUresult cuLaunchKernel(CUfunction f, unsigned gx, unsigned gy, unsigned gz, unsigned bx, unsigned by,
                        unsigned bz, unsigned shared, CUstream s, void **params, void **extra) {
    (void)s; (void)params; (void)extra;
    unsigned long long threads = (unsigned long long)bx * by * bz;
    if (!gx || !gy || !gz || !threads || threads > 1024 || bx > 1024 || by > 1024 || bz > 64 ||
        gy > 65535 || gz > 65535 || shared > (unsigned)MAX_SHARED_OPTIN) {
        fprintf(stderr, "offline CUDA driver: launch refused: grid %u×%u×%u, block %u×%u×%u, %u B shared\n",
                gx, gy, gz, bx, by, bz, shared);
        return INVALID_VALUE;
    }
    __atomic_fetch_add(&launches, 1, __ATOMIC_RELAXED);
    trace("L %s %u %u %u\n", (const char *)f, gx, gy, gz);
    return SUCCESS;
}

/* Tensor memory accelerator descriptors (autotune's TMA matmul and convolution candidates): an
 * opaque 128-byte map that nothing reads here. Only the first argument is used; the others are
 * the caller's to clean up (System V), so they are not declared. */
CUresult cuTensorMapEncodeTiled(void *map) { memset(map, 0, 128); return SUCCESS; }
CUresult cuTensorMapEncodeIm2col(void *map) { memset(map, 0, 128); return SUCCESS; }
CUresult cuTensorMapEncodeIm2colWide(void *map) { memset(map, 0, 128); return SUCCESS; }

/* NVRTC 13 looks for the driver (dlopen libcuda.so.1, cuInit, cuGetExportTable) for its own
 * compilation cache, and without cuGetExportTable it reads a table it never got: refuse it, and
 * NVRTC goes on without its cache. */
CUresult cuGetExportTable(const void **table, const void *uuid) {
    (void)uuid;
    *table = NULL;
    return NOT_SUPPORTED;
}

CUresult cuGetErrorString(CUresult r, const char **s) {
    *s = r == SUCCESS ? "no error" : "refused by the offline CUDA driver (tools/offline-cuda)";
    return SUCCESS;
}
CUresult cuGetErrorName(CUresult r, const char **s) {
    *s = r == SUCCESS ? "CUDA_SUCCESS" : r == INVALID_VALUE ? "CUDA_ERROR_INVALID_VALUE" : "CUDA_ERROR_OFFLINE";
    return SUCCESS;
}

/* What the process did, on exit (stderr): the modules loaded are the kernels compiled. */
__attribute__((destructor)) static void report(void) {
    if (modules || launches)
        fprintf(stderr, "offline CUDA driver: %zu modules loaded, %zu launches, %.1f MiB allocated\n",
                modules, launches, allocated / 1048576.0);
}
