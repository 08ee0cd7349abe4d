#!/usr/bin/env bash
# The GPU check, in two halves: `pack` on a CPU machine with cargo, `run` on the GPU machine.
#
#   tools/gpu-check.sh pack [DIR]          # default DIR: target/gpu-check
#   tools/gpu-check.sh run  [DIR] [OUT]    # default OUT: DIR/results
#
# pack builds, with CUDARC_CUDA_VERSION (default 13000: driver >= 580), the f3g binary and the
# parity test binaries of f3g-splat and f3g-nets with every GPU feature (CUDA and wgpu, one
# build of Burn for all of them), and one f3g with `cuda,autotune` (unless
# F3G_GPU_CHECK_AUTOTUNE=0), and downloads gsplat 1.5.3 (pure Python) and its small pure-Python dependencies
# from PyPI; it compiles the `paper` step's kernels for sm_90 on the offline driver into a kernel
# cache the run starts from; it strips the binaries, compresses them together (xz) and refuses a
# package of 64 MiB or more (what the GPU machine is given).
#
# run needs nothing but the package, python3 with PyTorch (CUDA) and the CUDA toolkit on the
# GPU machine (nvcc, for gsplat's first use; compute-sanitizer if present). Within about 9
# minutes it runs, each step under its own time limit and none stopping the others (a step the
# budget no longer covers is skipped). gsplat's CUDA compiles in the background from the start
# (minutes of nvcc on 8 host cores): the checks of correctness run beside it, every timed step
# after it (beside it, f3g's `paper` step took 1 039 ms against 770-811 ms alone, 2026-11-27,
# and every profiled launch about 20× its time, 2026-11-29):
#   1. `f3g devices --json`                  what the machine has (driver, NVRTC, include, NCCL)
#   2. the parity tests on cuda:0            splat kernels and networks against the CPU
#   3. compute-sanitizer racecheck, synccheck, initcheck on one splat test (the whole op,
#      forward and backward, on random scenes), when the tool is there
#   on request (F3G_GPU_CHECK_ONLY="gemm-sweep"): the convolutions' implicit-GEMM routines one
#      at a time (F3G_CONV_GEMM), `bench nets --paper` under each, then a `paper` step and the
#      network parity tests with the fastest
#   4. `f3g bench train --preset paper`      5 steps (random LPIPS VGG weights of the real
#      shapes where the real ones are not installed: tools/random_lpips_vgg.py), again with
#      `--unsynced` (no wait at each phase's end), then its PyTorch twin
#      tools/paper_step_torch.py (the same step's work with gsplat); the summary gives f3g's
#      step ÷ the twin's
#   5. tools/bench_gsplat.py, then `f3g bench splat --device cuda` on the same kind of scene
#   6. `f3g bench nets --device cuda --paper --image 512` twice (the first process compiles
#      what the kernel cache does not hold yet), without autotune, then tools/bench_nets_torch.py
#   7. the kernel profile of a `paper` run    each launch timed on the device (CubeCL's
#      profiler at its `profile-full` level, F3G_KERNEL_PROFILE), summed by kernel family
#      and by variant (a convolution's pass, the grid): profile.json, the top ones in
#      profile.md; placed in the step's phases by tools/phase_profile.py with the offline
#      driver's trace of the same command (trace.txt.xz, made at pack): phases.md
#   8. `f3g bench nets` with autotune         the paper body network, in what is left (only
#      when the package has the autotune binary: F3G_GPU_CHECK_AUTOTUNE=0 at pack leaves it
#      out, and 12 minutes of building)
# Beside all of it `nvidia-smi dmon` logs the card's clocks, power and load each second
# (dmon.log), so a slow step can be told from a slow card.
# and writes OUT/summary.json (each step: command, exit code, seconds, its JSON where it makes
# one) and OUT/summary.md, with each step's output in OUT/<step>.log, and all of OUT (less the
# kernel cache) as OUT.tar.gz: the one file to bring back.
set -uo pipefail
cd "$(dirname "$0")/.."

mode=${1:-}
dir=${2:-target/gpu-check}

pack() {
    set -e
    export CUDARC_CUDA_VERSION=${CUDARC_CUDA_VERSION:-13000}
    rm -rf "$dir" && mkdir -p "$dir/bin" "$dir/tests" "$dir/wheels" "$dir/tools"
    # The f3g binary and the parity test binaries from one build with every GPU feature
    # (`tools/cuda-offline.sh features`: CUDA and wgpu), one build of Burn for all of them
    # (another feature set rebuilds Burn: 36 min cold on two cores, 2026-11-27).
    # `cargo test --no-run` names every executable it built: the test binaries and the f3g
    # binary the CLI's tests run.
    cargo test --release --locked --no-run -p f3g-nets -p f3g-splat -p f3g-cli \
        --features "$(tools/cuda-offline.sh features)" --test gpu --message-format=json \
        | python3 -c '
import json, shutil, sys, tomllib
for line in sys.stdin:
    m = json.loads(line)
    if m.get("reason") != "compiler-artifact" or not m.get("executable"):
        continue
    # The package name from its manifest: package_id spells it in more than one way.
    with open(m["manifest_path"], "rb") as f:
        crate = tomllib.load(f)["package"]["name"]
    if m["target"]["kind"] == ["bin"] and m["target"]["name"] == "f3g":
        shutil.copy(m["executable"], sys.argv[1] + "/bin/f3g-cuda")
    elif m["target"]["name"] == "gpu" and crate in ("f3g-splat", "f3g-nets"):
        shutil.copy(m["executable"], sys.argv[1] + "/tests/" + crate + "-gpu")
' "$dir"
    ls "$dir/bin/f3g-cuda" "$dir/tests/f3g-splat-gpu" "$dir/tests/f3g-nets-gpu" >/dev/null
    if [ "${F3G_GPU_CHECK_AUTOTUNE:-1}" != 0 ]; then
        cargo build --release --locked -p f3g-cli --features cuda,autotune
        cp target/release/f3g "$dir/bin/f3g-cuda-autotune"
    fi
    # The offline driver's trace of the profiled command: which phase each launch belongs to
    # (tools/phase_profile.py; the offline CUDA toolkit's wheels, about 130 MB, on first use).
    # The same run fills a kernel cache the GPU machine starts from: the offline driver answers
    # as an sm_90 device and NVRTC 13.0 compiles for it as the H100's and H200's does (CubeCL
    # keys its PTX by architecture), so the `paper` step's kernels are compiled here, not in
    # device time (2026-11-30: a first process's two warm-up steps 10.6 s against 49.9 s cold).
    F3G_KERNEL_CACHE=$dir/kernel-cache \
        python3 tools/phase_profile.py trace "$dir/bin/f3g-cuda" "$dir/trace.txt" >"$dir/trace.log" 2>&1
    xz -9 "$dir/trace.txt" && rm "$dir/trace.log"
    tar -C "$dir/kernel-cache" -cf - . | xz -6 >"$dir/kernel-cache.tar.xz"
    rm -rf "$dir/kernel-cache"
    strip "$dir"/bin/* "$dir"/tests/*
    # One solid archive with a dictionary larger than any binary: the four binaries share most
    # of their code (Burn, CubeCL), so each compresses against the others (two f3g binaries
    # alone: 27.8 + 28.8 MB compressed one by one, 34.2 MB together).
    tar -C "$dir" -cf - bin tests | xz -T1 --lzma2=preset=6,dict=256MiB >"$dir/binaries.tar.xz"
    rm -rf "$dir/bin" "$dir/tests"
    # gsplat alone: its pure-Python dependencies (jaxtyping, wadler-lindig, rich and rich's) are
    # in the GPU machine's image. Its wheel carries GLM's documentation and tests (16 of its 22
    # MB unpacked), which the build never reads: dropped, so the package fits beside the tree.
    pip download --quiet --no-deps -d "$dir/wheels" gsplat==1.5.3
    python3 - "$dir"/wheels/gsplat-*.whl <<'PY'
import os, sys, zipfile
wheel = sys.argv[1]
with zipfile.ZipFile(wheel) as src, zipfile.ZipFile(wheel + ".tmp", "w", zipfile.ZIP_DEFLATED) as dst:
    for item in src.infolist():
        if "/third_party/glm/doc/" not in item.filename and "/third_party/glm/test/" not in item.filename:
            dst.writestr(item, src.read(item))
os.replace(wheel + ".tmp", wheel)
PY
    cp tools/bench_gsplat.py tools/bench_nets_torch.py tools/random_lpips_vgg.py \
        tools/kernel_profile.py tools/phase_profile.py tools/paper_step_torch.py "$dir/tools/"
    cp "$0" "$dir/gpu-check.sh"
    # What a device call carries is the package and the working tree (tracked files and
    # untracked ones git does not ignore) together.
    local size tree
    size=$(du -sb "$dir" | cut -f1)
    tree=$(git ls-files -z --cached --others --exclude-standard \
        | du -cb --files0-from=- 2>/dev/null | tail -1 | cut -f1)
    echo "package $dir: $((size / 1024 / 1024)) MiB ($size bytes), with the working tree" \
        "$(((size + tree) / 1024 / 1024)) MiB"
    du -sh "$dir/binaries.tar.xz" "$dir/wheels"
    if [ $((size + tree)) -ge $((64 * 1024 * 1024)) ]; then
        echo "the package and the working tree are 64 MiB or more: the GPU machine is given" \
            "at most 64 MiB (pack with F3G_GPU_CHECK_AUTOTUNE=0 for one f3g binary; still over," \
            "carry a test binary in a second call: docs/gpu.md, the GPU check)" >&2
        exit 1
    fi
}

run() {
    local out=${3:-$dir/results}
    mkdir -p "$out" "$dir/unpacked"
    out=$(cd "$out" && pwd)
    # The kernel cache pack made offline (the `paper` step's kernels), else a fresh one: the
    # first process compiles what the cache lacks, later ones load it.
    export F3G_KERNEL_CACHE=$out/kernel-cache
    rm -rf "$F3G_KERNEL_CACHE" && mkdir -p "$F3G_KERNEL_CACHE"
    [ -f "$dir/kernel-cache.tar.xz" ] && xz -dc "$dir/kernel-cache.tar.xz" | tar -C "$F3G_KERNEL_CACHE" -xf -
    xz -dc "$dir/binaries.tar.xz" | tar -C "$dir/unpacked" -xf -
    # (A package of test binaries alone, for a second call, has no bin/ and no wheels.)
    local part
    for part in bin tests; do
        [ -d "$dir/unpacked/$part" ] && mv "$dir/unpacked/$part"/* "$dir/unpacked/"
    done
    mkdir -p "$dir/python"
    for w in "$dir"/wheels/*.whl; do
        [ -e "$w" ] && python3 -m zipfile -e "$w" "$dir/python"
    done
    export PYTHONPATH="$PWD/$dir/python${PYTHONPATH:+:$PYTHONPATH}"
    # NVRTC and NCCL where the loader does not find them: CUDA's and pip's folders.
    local lib found
    for lib in libnvrtc.so libnccl.so; do
        if ! ldconfig -p | grep -q "$lib"; then
            found=$(find /usr/local/cuda*/ /opt -name "$lib*" -print -quit 2>/dev/null)
            [ -n "$found" ] && export LD_LIBRARY_PATH="$(dirname "$found")${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
        fi
    done
    local bin=$dir/unpacked
    local f3g=$bin/f3g-cuda-autotune
    [ -x "$f3g" ] || f3g=$bin/f3g-cuda
    local started=$SECONDS
    : >"$out/steps.jsonl"
    # step NAME LIMIT_S JSON_OR_- COMMAND...: runs it, logs it, records it.
    # Each step's limit is cut to what is left of the whole check's budget (F3G_GPU_CHECK_BUDGET
    # seconds, default 520: under 9 minutes); a step with under 10 s left is skipped (exit 125).
    local budget=${F3G_GPU_CHECK_BUDGET:-520}
    # F3G_GPU_CHECK_ONLY="step step …" runs those steps alone (a rerun after a fix).
    local only=${F3G_GPU_CHECK_ONLY:-}
    step() {
        local name=$1 limit=$2 json=$3
        shift 3
        if [ -n "$only" ] && [[ " $only " != *" $name "* ]]; then
            return
        fi
        local left=$((budget - (SECONDS - started)))
        [ "$limit" -gt "$left" ] && limit=$left
        echo "== $name (at most ${limit} s): $*"
        local t0=$SECONDS rc=125
        if [ "$limit" -ge 10 ]; then
            timeout "$limit" "$@" >"$out/$name.log" 2>&1
            rc=$?
        else
            echo "skipped: the check's budget is spent" >"$out/$name.log"
        fi
        tail -n 5 "$out/$name.log"
        python3 - "$name" "$rc" "$((SECONDS - t0))" "$json" "$*" >>"$out/steps.jsonl" <<'PY'
import json, os, sys
name, rc, secs, js, cmd = sys.argv[1:]
result = None
if js != "-" and os.path.exists(js):
    with open(js) as f:
        result = json.load(f)
print(json.dumps({"step": name, "command": cmd, "exit": int(rc), "seconds": int(secs),
                  "timed_out": rc in ("124", "137"), "result": result}))
PY
    }
    local dmon=0
    if command -v nvidia-smi >/dev/null; then
        nvidia-smi dmon -s pucm -o T >"$out/dmon.log" 2>&1 &
        dmon=$!
    fi
    # gsplat compiles its CUDA at first use (minutes of nvcc): start that now, beside the steps
    # that follow (they use one host core), and time gsplat only once it is built.
    # (Not when F3G_GPU_CHECK_ONLY leaves gsplat out: eight compilers would share the host with
    # the timed steps.)
    export TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0} MAX_JOBS=${MAX_JOBS:-8}
    local gsplat_build=0
    # (F3G_GPU_CHECK_ONLY="gsplat-build bench-step-torch" reruns the PyTorch twin alone.)
    if [ -z "$only" ] || [[ " $only " == *" gsplat-build "* || " $only " == *" bench-gsplat "* \
        || " $only " == *" bench-step-torch "* ]]; then
        python3 -c 'from gsplat.cuda._backend import _C' >"$out/gsplat-build.log" 2>&1 &
        gsplat_build=$!
    fi
    # The paper preset's LPIPS is VGG; its weights (59 MB) do not travel. Where they are not
    # installed, random weights of the real shapes stand in: the work timed is the same.
    export F3G_WEIGHTS=${F3G_WEIGHTS:-$PWD/$dir/weights}
    if [ ! -e "$F3G_WEIGHTS/lpips-vgg.safetensors" ]; then
        step vgg-weights 60 - python3 "$dir/tools/random_lpips_vgg.py" \
            "$F3G_WEIGHTS/lpips-vgg.safetensors"
    fi
    step devices 30 "$out/devices.json" sh -c "'$f3g' devices --json >'$out/devices.json'"
    export F3G_TEST_DEVICE=cuda
    step splat-parity 120 - "$bin/f3g-splat-gpu" --test-threads 1
    step nets-parity 120 - "$bin/f3g-nets-gpu" --test-threads 1
    if command -v compute-sanitizer >/dev/null; then
        for tool in racecheck synccheck initcheck; do
            step "sanitizer-$tool" 45 - compute-sanitizer --tool "$tool" --error-exitcode 9 \
                "$bin/f3g-splat-gpu" --test-threads 1 --exact \
                the_op_matches_the_cpu_on_random_scenes
        done
    fi
    # The convolutions' implicit-GEMM routines one at a time (`F3G_CONV_GEMM`, see
    # crates/nets/src/conv/cube.rs): the paper StyleUNets' forward and forward+backward under
    # each (F3G_GPU_CHECK_GEMMS, `default` = Burn's synchronous cyclic CMMA routine), then a
    # `paper` step and the network parity tests with the fastest forward and backward found
    # (gemm-choice.txt): the StyleUNets alone can mislead, the step (its LPIPS VGG and
    # discriminator shapes too) is the judge. Only on request: `gemm-sweep` in
    # F3G_GPU_CHECK_ONLY runs all of these.
    if [[ " $only " == *" gemm-sweep "* ]]; then
        local g gemms=${F3G_GPU_CHECK_GEMMS:-default simple_async_tma_cmma specialized_tma_cmma \
            simple_async_cyclic_cmma specialized_async_cyclic_cmma simple_sync_cyclic_mma \
            simple_async_cyclic_mma specialized_async_cyclic_mma simple_sync_strided_cmma \
            simple_sync_tilewise_cmma}
        local only_before=$only
        only=""
        for g in $gemms; do
            # The first process compiles every kernel (a cold cache: about a minute on an
            # H200), later ones only their routine's: 45 s each timed out on 2026-11-27.
            step "gemm-$g" "$([ "$g" = "${gemms%% *}" ] && echo 120 || echo 75)" \
                "$out/gemm-$g.json" sh -c "[ '$g' = default ] \
                || export F3G_CONV_GEMM='$g'; '$bin/f3g-cuda' bench nets --device cuda --paper \
                --image 512 --only paper --repeats 3 --json '$out/gemm-$g.json'"
        done
        python3 - "$out" $gemms >"$out/gemm-choice.txt" <<'PY'
import json, os, sys
out, names = sys.argv[1], sys.argv[2:]
fwd, bwd = {}, {}
for name in names:
    path = f"{out}/gemm-{name}.json"
    if not os.path.exists(path):
        continue
    rows = json.load(open(path))
    fwd[name] = sum(r["forward_ms"] for r in rows)
    bwd[name] = sum(r["forward_backward_ms"] - r["forward_ms"] for r in rows)
    print(f"{name}: forward {fwd[name]:.1f} ms, backward {bwd[name]:.1f} ms", file=sys.stderr)
best = lambda times: min(times, key=times.get) if times else "default"
f, b = best(fwd), best(bwd)
parts = [f"{p}:{n}" for p, n in (("forward", f), ("input", b), ("weight", b)) if n != "default"]
print(",".join(parts))
PY
        local choice
        choice=$(cat "$out/gemm-choice.txt")
        echo "== the fastest routines: F3G_CONV_GEMM=$choice"
        step bench-train-paper-gemm 150 "$out/train-paper-gemm.json" sh -c \
            "F3G_CONV_GEMM='$choice' '$bin/f3g-cuda' bench train --preset paper --device cuda \
            --steps 5 --warmup 1 --json '$out/train-paper-gemm.json'"
        step nets-parity-gemm 120 - env F3G_CONV_GEMM="$choice" "$bin/f3g-nets-gpu" \
            --test-threads 1
        only=$only_before
    fi
    step gsplat-build 120 - sh -c "while kill -0 $gsplat_build 2>/dev/null; do sleep 1; done; \
        cat '$out/gsplat-build.log'; python3 -c 'from gsplat.cuda._backend import _C'"
    # The timed steps from here on, after gsplat's build: an 8-job nvcc build beside f3g's `paper`
    # step made it 1 039 ms against 770-811 ms alone (BENCHMARKS, 2026-11-27).
    # 5 timed steps after 2 warm-ups: making the 1536×2048 capture, the run's setup and the
    # cold compilation come first (with 20 steps it did not end within 150 s on the H200). Two
    # warm-ups, as the twin's: after one, the GPU memory in use still grew from 26 to 33 GB in
    # the first timed step of every run (2026-11-29).
    step bench-train-paper 150 "$out/train-paper.json" "$bin/f3g-cuda" bench train \
        --preset paper --device cuda --steps 5 --warmup 2 --json "$out/train-paper.json"
    # The same steps as training runs them, without a synchronisation at each phase's end: the
    # difference is what the phase timer's waits cost.
    step bench-train-paper-unsynced 90 "$out/train-paper-unsynced.json" "$bin/f3g-cuda" bench \
        train --preset paper --device cuda --steps 5 --warmup 2 --unsynced \
        --json "$out/train-paper-unsynced.json"
    # The PyTorch twin of the `paper` step just timed (same networks, Gaussians, render sizes,
    # LPIPS, discriminator step and Adam; tools/paper_step_torch.py's docstring maps its phases
    # to f3g's), with the same 2 warm-ups + 5 timed steps. It renders with gsplat: its build
    # awaited first (done by the gsplat-build step unless F3G_GPU_CHECK_ONLY left that out).
    step bench-step-torch 75 "$out/step-torch.json" sh -c "while [ $gsplat_build -gt 0 ] \
        && kill -0 $gsplat_build 2>/dev/null; do sleep 1; done; \
        python3 '$dir/tools/paper_step_torch.py' --device cuda --steps 5 --warmup 2 \
        --json '$out/step-torch.json'"
    step bench-gsplat 90 "$out/gsplat.json" python3 "$dir/tools/bench_gsplat.py" --repeats 5 \
        --json "$out/gsplat.json"
    step bench-splat 60 "$out/splat.json" "$bin/f3g-cuda" bench splat --device cuda --repeats 5 \
        --json "$out/splat.json"
    step bench-nets-cold 120 "$out/nets-cold.json" "$bin/f3g-cuda" bench nets --device cuda \
        --paper --image 512 --json "$out/nets-cold.json"
    step bench-nets-warm 60 "$out/nets-warm.json" "$bin/f3g-cuda" bench nets --device cuda \
        --paper --image 512 --json "$out/nets-warm.json"
    step bench-nets-torch 60 "$out/nets-torch.json" python3 "$dir/tools/bench_nets_torch.py" \
        --paper --image 512 --json "$out/nets-torch.json"
    # Every launch timed on the device: where a `paper` step's GPU time goes, kernel by kernel.
    # The profile holds the warm-up step's launches and the timed step's (halve its totals for
    # one step); compiling is not a launch, so it is not in them.
    # At CubeCL's `profile-full` level, so each variant is named by its pass and grid.
    # After gsplat's build too: beside it (14 nvcc jobs) every launch's time came out about 20×
    # the quiet machine's (2026-11-29).
    step profile-train-paper 120 "$out/profile.json" sh -c "CUBECL_DEBUG_OPTION=profile-full \
        F3G_KERNEL_PROFILE='$out/profile.log' \
        '$bin/f3g-cuda' bench train --preset paper --device cuda --steps 1 --warmup 1 \
        && python3 '$dir/tools/kernel_profile.py' '$out/profile.log' --json '$out/profile.json' \
        --markdown '$out/profile.md' && { [ ! -f '$dir/trace.txt.xz' ] \
        || python3 '$dir/tools/phase_profile.py' join '$dir/trace.txt.xz' '$out/profile.log' \
        --json '$out/phases.json' --markdown '$out/phases.md'; }"
    # Last: autotune compiles and times every candidate kernel of every shape (750 kernels for
    # the first network on the CPU machine's NVRTC); it gets what is left of the budget.
    # The paper-sized body network alone: the one Burn's untuned kernels are slowest on.
    if [ -x "$bin/f3g-cuda-autotune" ]; then
        step bench-nets-autotune 180 "$out/nets-autotune.json" "$f3g" bench nets --device cuda \
            --paper --image 512 --only "body paper" --json "$out/nets-autotune.json"
    fi
    [ "$dmon" -gt 0 ] && kill "$dmon" 2>/dev/null
    python3 - "$out" "$((SECONDS - started))" <<'PY'
import json, sys
out, total = sys.argv[1], int(sys.argv[2])
steps = [json.loads(l) for l in open(f"{out}/steps.jsonl")]
# f3g's `paper` step against its PyTorch twin, when both ran in this check and wrote their
# JSON: f3g's `step_ms` is the mean wall clock of its timed steps, so the twin's mean is the
# one compared (its median, its own `step_ms`, is shown beside it).
ratio, ratio_line = None, ""
ran = {s["step"]: s["result"] for s in steps if s["exit"] == 0 and s["result"]}
try:
    f3g_ms = ran["bench-train-paper"]["step_ms"]
    twin = ran["bench-step-torch"]
    torch_ms, torch_median = twin.get("step_ms_mean", twin["step_ms"]), twin["step_ms"]
    ratio = {"f3g_step_ms": f3g_ms, "torch_step_ms_mean": torch_ms,
             "torch_step_ms_median": torch_median, "ratio": f3g_ms / torch_ms}
    ratio_line = (f"f3g paper step ÷ PyTorch twin step (means): {f3g_ms:.1f} ms / "
                  f"{torch_ms:.1f} ms = {f3g_ms / torch_ms:.2f}× (twin's median "
                  f"{torch_median:.1f} ms)")
except (KeyError, TypeError, ZeroDivisionError):
    pass
with open(f"{out}/summary.json", "w") as f:
    json.dump({"seconds": total, "steps": steps, "paper_step_vs_torch": ratio}, f, indent=1)
rows = ["| step | exit | seconds | note |", "|---|---|---|---|"]
for s in steps:
    note = ("timed out" if s["timed_out"] else "skipped (budget)" if s["exit"] == 125
            else "ok" if s["exit"] == 0 else "failed: see the log")
    rows.append(f"| {s['step']} | {s['exit']} | {s['seconds']} | {note} |")
if ratio_line:
    rows += ["", ratio_line]
with open(f"{out}/summary.md", "w") as f:
    f.write(f"# GPU check ({total} s)\n\n" + "\n".join(rows) + "\n")
print("\n".join(rows))
PY
    # Everything in one file beside OUT (a device call brings back only a few files): the
    # logs, JSON and profile, without the kernel cache.
    rm -rf "$out/kernel-cache"
    [ -f "$out/profile.log" ] && gzip -f "$out/profile.log"
    tar -C "$(dirname "$out")" -czf "$out.tar.gz" "$(basename "$out")"
    echo "results: $out.tar.gz ($(du -h "$out.tar.gz" | cut -f1))"
}

case "$mode" in
pack) pack ;;
run) run "$@" ;;
*)
    sed -n '2,30p' "$0"
    exit 2
    ;;
esac
