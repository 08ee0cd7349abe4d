#!/usr/bin/env bash
# CUDA without a GPU: NVIDIA's compilers from PyPI, and a driver that compiles but never runs.
#
#   tools/cuda-offline.sh setup [DIR]     # NVIDIA's CUDA 13.0 wheels from PyPI, unpacked into DIR
#                                         # (default target/cuda-offline), and the offline driver
#                                         # built there; prints what to export
#   tools/cuda-offline.sh test  [DIR]     # setup, then the checks: every splat kernel through
#                                         # NVRTC and ptxas (crates/splat/tests/cuda_kernels.rs),
#                                         # a training step on the offline driver, cold then from
#                                         # the kernel cache (crates/cli/tests/cuda_offline.rs);
#                                         # F3G_GPU_CARGO_CONFIG=FILE: cargo --config for its build
#   tools/cuda-offline.sh test-binaries   # `test`'s build alone: prints the test executables
#   tools/cuda-offline.sh run-tests BIN…  # `test`'s run alone, of those executables (so that
#                                         # cargo is free for other work while they run: CI)
#   tools/cuda-offline.sh run F3G ARGS…   # setup, then `F3G ARGS…` (a `cuda` build of f3g) against
#                                         # the offline driver, e.g. `bench train --device cuda`
#   tools/cuda-offline.sh features        # every GPU feature of the crates with GPU tests
#   tools/cuda-offline.sh ci-features     # those and f3g-splat/cuda-source: CI's GPU build
#
# The wheels (about 130 MB, pinned): nvidia-cuda-nvrtc (libnvrtc.so.13 and its builtins),
# nvidia-cuda-runtime and nvidia-cuda-crt (CUDA's headers, which NVRTC includes: the tensor-core
# matmuls need crt/mma.h), nvidia-cuda-cccl (the cccl headers
# cubecl-cuda adds to the include path), nvidia-cuda-nvcc (ptxas). NVRTC compiles CUDA C to PTX
# and ptxas PTX to SASS without a device. The offline driver (tools/offline-cuda/libcuda.c)
# answers as one H100 that accepts every module and launch and executes nothing: with it a
# `cuda` build of f3g compiles every kernel a command launches, exactly as on a GPU, and reports
# how many (its results are zeros). CUDA_PATH is set as cubecl-cuda reads it.
set -euo pipefail
cd "$(dirname "$0")/.."

mode=${1:-}
dir=${2:-target/cuda-offline}
# Every GPU feature of the crates with GPU tests (`features` prints it): tools/gpu-check.sh
# builds the GPU machine's f3g and parity tests with it, one build for CUDA and wgpu.
GPU_TEST_FEATURES=f3g-cli/gpu,f3g-cli/cuda,f3g-nets/gpu,f3g-nets/cuda,f3g-splat/gpu,f3g-splat/cuda
# CI's one GPU build (`ci-features`): those and the splat kernels' test-only CUDA sources.
CI_FEATURES=$GPU_TEST_FEATURES,f3g-splat/cuda-source

setup() {
    if [ ! -x "$dir/nvidia/cu13/bin/ptxas" ] || [ ! -f "$dir/nvidia/cu13/include/crt/mma.h" ]; then
        mkdir -p "$dir/wheels"
        python3 -m pip download --quiet --no-deps -d "$dir/wheels" \
            nvidia-cuda-nvrtc==13.0.88 nvidia-cuda-runtime==13.0.88 nvidia-cuda-crt==13.0.88 \
            nvidia-cuda-cccl==13.0.85 nvidia-cuda-nvcc==13.0.88
        for wheel in "$dir"/wheels/*.whl; do python3 -m zipfile -e "$wheel" "$dir"; done
        chmod +x "$dir/nvidia/cu13/bin/"*
        rm -rf "$dir/wheels"
    fi
    CUDA_PATH=$(cd "$dir/nvidia/cu13" && pwd)
    export CUDA_PATH
    export LD_LIBRARY_PATH=$CUDA_PATH/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
    mkdir -p "$dir/driver"
    cc -shared -fPIC -O1 -Wall -Wextra -Werror -o "$dir/driver/libcuda.so.1" tools/offline-cuda/libcuda.c
    ln -sf libcuda.so.1 "$dir/driver/libcuda.so"
    driver=$(cd "$dir/driver" && pwd)
}

# The checks' test executables, built as CI's GPU build builds them: printed one per line.
test_binaries() {
    export CUDARC_CUDA_VERSION=${CUDARC_CUDA_VERSION:-13000}
    # Built without CUDA_PATH, as every other build here: cudarc's build script reruns (and with
    # it all of Burn) when CUDA_PATH changes. The packages and features of CI's GPU build
    # (`ci-features`), so .ci/run's lavapipe tests and these share one build of Burn; with
    # F3G_GPU_CARGO_CONFIG (a cargo `--config` file) as that build had it (CI's: .ci/gpu-build.toml).
    (env -u CUDA_PATH cargo test ${F3G_GPU_CARGO_CONFIG:+--config "$F3G_GPU_CARGO_CONFIG"} \
        --release --locked -p f3g-cli -p f3g-nets -p f3g-splat \
        --features "$CI_FEATURES" --test cuda_offline --test cuda_kernels --no-run \
        --message-format=json-render-diagnostics) | python3 -c '
import json, sys
for line in sys.stdin:
    m = json.loads(line)
    if m.get("reason") == "compiler-artifact" and m.get("executable") and m["target"]["kind"] == ["test"]:
        print(m["executable"])
'
}

# Runs test executables (as `test-binaries` prints them) against NVRTC from PyPI and the offline
# driver.
run_tests() {
    [ $# -gt 0 ] || { echo "run-tests: no test executables given" >&2; exit 2; }
    setup
    export F3G_OFFLINE_CUDA_DRIVER=$driver
    for test in "$@"; do
        "$test" --nocapture --test-threads 1
    done
}

case "$mode" in
features)
    echo "$GPU_TEST_FEATURES"
    ;;
ci-features)
    echo "$CI_FEATURES"
    ;;
setup)
    setup
    echo "export CUDA_PATH=$CUDA_PATH"
    echo "export LD_LIBRARY_PATH=$LD_LIBRARY_PATH"
    echo "# and, for the offline driver instead of a real one:"
    echo "export LD_LIBRARY_PATH=$driver:\$LD_LIBRARY_PATH"
    ;;
run)
    f3g=${2:?the f3g binary (a cuda build) to run}
    shift 2
    dir=target/cuda-offline
    setup
    LD_LIBRARY_PATH=$driver:$LD_LIBRARY_PATH "$f3g" "$@"
    ;;
test-binaries)
    test_binaries
    ;;
run-tests)
    shift
    dir=target/cuda-offline
    run_tests "$@"
    ;;
test)
    binaries=$(test_binaries)
    # shellcheck disable=SC2086 # one executable path per word
    run_tests $binaries
    ;;
*)
    sed -n '2,27p' "$0"
    exit 2
    ;;
esac
