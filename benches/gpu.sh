#!/usr/bin/env bash
# benches/gpu.sh: the one-shot check of texavatars on a machine with a GPU (issue 21.6).
#
#   bash benches/gpu.sh            # from the repository root or anywhere
#
# 1. builds the release binary (GPU_SH_PROFILE);
# 2. runs the GPU parity tests (the CubeCL kernels against their CPU references and the
#    WGSL validation) on the machine's wgpu adapter;
# 3. `bench fps` at paper scale (configs/paper.json networks, 550 x 802) on wgpu;
# 4. one training step at paper scale (configs/train_paper.json, 550 x 802, batch 1) on wgpu
#    (`cargo bench --bench train`), with its kernel launches and blocking reads per step;
# and prints one table. Logs go to $GPU_SH_OUT (default $CARGO_TARGET_DIR/gpu-sh/, else
# target/gpu-sh/). Budget: under 10 minutes on a 16-core machine with a GPU; the release
# build is most of it from a clean clone. Please report the table (issue tracker or
# README's figures).
#
# GPU_SH_CUDA=1 builds with `--features cuda` and adds the same two measurements on burn's
# CUDA backend (NVIDIA GPUs).
#
# GPU_SH_QUICK=1 shrinks every stage (cpu networks, 138 x 200, few renders): a smoke test of
# the script itself, e.g. on lavapipe; its figures say nothing about a GPU.
#
# GPU_SH_PROFILE=dev builds and measures in the dev profile instead of release (the test
# build's artifacts; for the smoke test, not for figures).
#
# A GPU machine without Rust: GPU_SH_PACK=1 builds here and copies the four executables
# (texavatars, the two parity test binaries, the training-step benchmark) into
# $GPU_SH_OUT/bin, then stops; on the GPU machine, in a checkout of the same commit (for
# configs/), GPU_SH_BIN=<that folder> runs stages 2-4 with them instead of building.
set -euo pipefail
cd "$(dirname "$0")/.."
target=${CARGO_TARGET_DIR:-target}
out=${GPU_SH_OUT:-$target/gpu-sh}
mkdir -p "$out"
quick=${GPU_SH_QUICK:-0}
cuda=${GPU_SH_CUDA:-0}
features=()
backends=(wgpu)
if [ "$cuda" = 1 ]; then
    features=(--features cuda)
    backends=(wgpu cuda)
fi
if [ "$quick" = 1 ]; then
    net=configs/cpu.json; size=138x200; renders=5; rounds=1; bench_config=cpu
else
    net=configs/paper.json; size=550x802; renders=100; rounds=3; bench_config=paper
fi
t0=$(date +%s)
stage() { echo "gpu.sh: $* ($(( $(date +%s) - t0 )) s)" >&2; }

profile=${GPU_SH_PROFILE:-release}
profile_dir=$profile
if [ "$profile" = dev ]; then profile_dir=debug; fi
# `cargo bench` without --profile uses the bench profile, which inherits release and shares
# its artifacts.
bench_profile=()
if [ "$profile" != release ]; then bench_profile=(--profile "$profile"); fi
# The path of the executable a `--message-format=json` build made for target $1.
executable() { grep -o "\"executable\":\"[^\"]*/$1-[0-9a-f]*\"" | sed 's/.*":"//; s/"$//' | tail -n 1; }
if [ -n "${GPU_SH_BIN:-}" ]; then
    bin=$GPU_SH_BIN
    profile="$profile (prebuilt, $bin)"
    stage "1/4 prebuilt executables in $bin"
    for e in texavatars gpu_kernels splat_gpu train; do
        [ -x "$bin/$e" ] || { echo "gpu.sh: GPU_SH_BIN=$bin has no executable $e" >&2; exit 1; }
    done
else
    stage "1/4 build ($profile profile)"
    bin=$out/bin
    mkdir -p "$bin"
    cargo build --profile "$profile" "${features[@]}" --bin texavatars 2>&1 | tail -n 3 >&2
    cp "$target/$profile_dir/texavatars" "$bin/texavatars"
    cargo test --profile "$profile" "${features[@]}" --no-run --message-format=json \
        --test gpu_kernels --test splat_gpu >"$out/build_tests.json"
    cargo bench "${bench_profile[@]}" "${features[@]}" --no-run --message-format=json \
        --bench train >"$out/build_bench.json"
    for e in gpu_kernels splat_gpu; do
        cp "$(executable "$e" <"$out/build_tests.json")" "$bin/$e"
    done
    cp "$(executable train <"$out/build_bench.json")" "$bin/train"
    git describe --always --dirty >"$bin/commit" 2>/dev/null || echo unknown >"$bin/commit"
    if [ "${GPU_SH_PACK:-0}" = 1 ]; then
        echo "gpu.sh: executables in $bin; on the GPU machine: GPU_SH_BIN=<copy of it> bash benches/gpu.sh"
        exit 0
    fi
fi
exe="$bin/texavatars"

stage "2/4 GPU parity tests (wgpu)"
adapter=$(vulkaninfo --summary 2>/dev/null | grep -m1 -E "deviceName" | sed 's/.*= //' || true)
: >"$out/tests.log"
tests_ok=1
for e in gpu_kernels splat_gpu; do
    "$bin/$e" >>"$out/tests.log" 2>&1 || tests_ok=0
done
if [ "$tests_ok" = 1 ]; then
    tests="passed ($(grep -h '^test result' "$out/tests.log" | awk '{s += $4} END {print s}') tests)"
else
    tests="FAILED (see $out/tests.log)"
fi

declare -A fps step launches
for b in "${backends[@]}"; do
    stage "3/4 bench fps ($net, $size, $b)"
    "$exe" bench fps --backend "$b" --net "$net" --size "$size" --renders "$renders" \
        --rounds "$rounds" >"$out/fps_$b.log" 2>&1 || true
    f=$(grep -m1 "mean of" "$out/fps_$b.log" | sed 's/^mean of [0-9]* rounds: //' || true)
    fps[$b]=${f:-failed (see $out/fps_$b.log)}

    stage "4/4 training step ($bench_config, $b)"
    TEXAVATARS_BENCH_CONFIG=$bench_config TEXAVATARS_BENCH_BACKEND=$b \
        "$bin/train" --bench >"$out/train_$b.log" 2>&1 || true
    t=$(grep -A2 "train_iteration_" "$out/train_$b.log" | grep -m1 -oE "time: +\[[^]]*\]" || true)
    step[$b]=${t:-failed (see $out/train_$b.log)}
    l=$(grep -m1 "^launches per training step" "$out/train_$b.log" | sed 's/^launches per training step ([^)]*): //' || true)
    launches[$b]=${l:-not printed (see $out/train_$b.log)}
done

total=$(( $(date +%s) - t0 ))
{
    echo
    echo "| texavatars on $(hostname), $(date -u +%Y-%m-%d) | |"
    echo "|---|---|"
    echo "| commit | $(cat "$bin/commit" 2>/dev/null || git describe --always --dirty 2>/dev/null || echo unknown) |"
    echo "| cargo profile | $profile |"
    echo "| GPU | $(nvidia-smi --query-gpu=name,memory.total --format=csv,noheader 2>/dev/null | head -n1 || echo unknown) |"
    echo "| Vulkan device | ${adapter:-unknown (vulkaninfo not installed)} |"
    echo "| parity tests (gpu_kernels, splat_gpu) | $tests |"
    for b in "${backends[@]}"; do
        echo "| bench fps, $net, $size, $b | ${fps[$b]} |"
        echo "| training step, train_$bench_config, $b | ${step[$b]} |"
        echo "| kernel launches per step; the splat's blocking reads per step, $b | ${launches[$b]} |"
    done
    echo "| wall time of this script | ${total} s |"
    if [ "$quick" = 1 ]; then
        echo "| note | GPU_SH_QUICK=1: smoke test, not a measurement |"
    fi
} | tee "$out/table.md"
