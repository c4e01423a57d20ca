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
# and prints one table. Logs go to $GPU_SH_OUT (default target/gpu-sh/). Budget: under 10
# minutes on a 16-core machine with a GPU; the release build is most of it from a clean
# clone. Please report the table (issue tracker or README's figures).
#
# GPU_SH_CUDA=1 builds with `--features cuda` and adds the same two measurements on burn's
# CUDA backend (NVIDIA GPUs).
#
# GPU_SH_QUICK=1 shrinks every stage (cpu networks, 138 x 200, few renders): a smoke test of
# the script itself, e.g. on lavapipe; its figures say nothing about a GPU.
#
# GPU_SH_PROFILE=dev builds and measures in the dev profile instead of release (the test
# build's artifacts; for the smoke test, not for figures).
set -euo pipefail
cd "$(dirname "$0")/.."
out=${GPU_SH_OUT:-target/gpu-sh}
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
target=${CARGO_TARGET_DIR:-target}
t0=$(date +%s)
stage() { echo "gpu.sh: $* ($(( $(date +%s) - t0 )) s)" >&2; }

profile=${GPU_SH_PROFILE:-release}
profile_dir=$profile
if [ "$profile" = dev ]; then profile_dir=debug; fi
stage "1/4 build ($profile profile)"
cargo build --profile "$profile" "${features[@]}" 2>&1 | tail -n 3 >&2
exe="$target/$profile_dir/texavatars"

stage "2/4 GPU parity tests (wgpu)"
adapter=$(vulkaninfo --summary 2>/dev/null | grep -m1 -E "deviceName" | sed 's/.*= //' || true)
if cargo test --profile "$profile" "${features[@]}" --test gpu_kernels --test splat_gpu >"$out/tests.log" 2>&1; then
    tests="passed ($(grep -h 'test result' "$out/tests.log" | awk '{s += $4} END {print s}') tests)"
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
        cargo bench --profile "$profile" "${features[@]}" --bench train >"$out/train_$b.log" 2>&1 || true
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
    echo "| commit | $(git rev-parse --short HEAD 2>/dev/null || echo unknown) |"
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
