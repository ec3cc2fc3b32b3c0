#!/usr/bin/env bash
# A GPU lease in one call: scripts/gpu_check.sh OUT_DIR (the device's $OUT), from the repository root, with the
# wheels in .whl/ and the data in .gpu_data/ (what fits the lease's 64 MiB: lego with 25 of its train views and 5 val
# views at 800x800, fox, moldGoldCape's images_4 and masks_4). In this order, each step guarded (a failure goes on to
# the next) and cut to the time left before GPU_CHECK_DEADLINE seconds:
#   a. setup: the wheels into /tmp/site, the project on PYTHONPATH; torch, CUDA and the GPU's name
#   b. the README's test command (CUDA where there is one) over pytest-xdist workers, bounded to GPU_CHECK_TEST_SECONDS
#   rows of scripts/gpu_check.yaml through nerf-bench, one at a time (timed; nothing beside them):
#   splat:    splat_blender_gpu, lego 800x800, 2 minutes             -> OUT/splat.json
#   splatfox: splat_360_gpu, fox, 2 minutes                          -> OUT/splatfox.json
#   fast:     fast_blender_gpu, lego 800x800 (compiled)              -> OUT/fast.json
#   cape:     nerfacto_360_gpu, moldGoldCape masked, downscale 4     -> OUT/cape.json
#   capesplat: splat_object_gpu, moldGoldCape masked, downscale 4, 4 minutes -> OUT/capesplat.json (its Gaussians
#             start from points triangulated inside the masks: carry pycolmap's wheel in .whl/, else they start at random;
#             its 38 MB fit the lease's 64 MiB beside `gpu_check_tools.py data ... --scenes moldGoldCape` alone)
#   (syncs: issue 47's CountHostSyncs over plain fast_blender_gpu steps, when named)
# then OUT/summary.txt. OUT gets (8 files at most come back: the four below and the five rows' JSON are nine, and
# syncs adds one more, so name fewer steps): log.txt (everything), summary.txt, junit_device.xml (the test files that touch a
# GPU, run first), junit.xml (the rest) and the rows' JSON.
#   GPU_CHECK_STEPS="tests splat splatfox fast cape"  the steps to run
#   GPU_CHECK_DEADLINE=565  seconds from the start by which everything has ended (the run tool's limit is 600)
#   GPU_CHECK_SMOKE=1  on a CPU: the project's .venv, no wheels, rows of seconds on tiny views (checks the plumbing)
#   GPU_CHECK_TEST_SECONDS=120  the tests' bound; GPU_CHECK_TEST_THREADS=1  CPU threads (torch's and numba's) a test worker
set -u
OUT=${1:?usage: scripts/gpu_check.sh OUT_DIR}
mkdir -p "$OUT" && OUT=$(cd "$OUT" && pwd)
REPO=$(cd "$(dirname "$0")/.." && pwd)
cd "$REPO" || exit 1
export PYTHONUNBUFFERED=1
START=$(date +%s)
SMOKE=${GPU_CHECK_SMOKE:-0}
STEPS=" ${GPU_CHECK_STEPS:-tests splat splatfox fast cape} "
DEADLINE=${GPU_CHECK_DEADLINE:-565}
TEST_SECONDS=${GPU_CHECK_TEST_SECONDS:-120}
WORK=${GPU_CHECK_WORK:-/tmp/gpu_check}
DATA=$REPO/.gpu_data
SUITE=scripts/gpu_check.yaml
LOG=$OUT/log.txt
rm -rf "$WORK" && mkdir -p "$WORK"
: >"$LOG"

say() { echo "[gpu_check +$(($(date +%s) - START))s] $*" | tee -a "$LOG"; }
left() { echo $((START + DEADLINE - $(date +%s))); }
stamp() { date '+%Y/%m/%d %H:%M:%S'; }
phase() { printf '%s\t%s\t%s\n' "$1" "$2" "$(stamp)" >>"$WORK/phases.txt"; }  # name, its start: ended now
wants() { [[ "$STEPS" == *" $1 "* ]]; }
cut() { say "CUT: $*"; echo "CUT: $*" >>"$WORK/cut.txt"; }

# ---- a. setup -----------------------------------------------------------------------------------------------------
if [ "$SMOKE" = 1 ]; then
    PY=${GPU_CHECK_PYTHON:-$REPO/.venv/bin/python}
    export PYTHONPATH=$REPO
    say "smoke run on this machine's CPU with $PY: no wheels, tiny rows"
    # moldGoldCape at downscale 16 (its smoke row): images_16 and masks_16 made from the carried images_4 and masks_4
    SMOKE_DATA=$WORK/smoke_data
    mkdir -p "$SMOKE_DATA/masked_objects" && ln -sfn "$DATA/nerf_synthetic" "$SMOKE_DATA/nerf_synthetic" && ln -sfn "$DATA/nerfstudio" "$SMOKE_DATA/nerfstudio"
    $PY - "$DATA/masked_objects/moldGoldCape" "$SMOKE_DATA/masked_objects/moldGoldCape" <<'PYTHON' || say "smoke: no small moldGoldCape"
import shutil, sys
from pathlib import Path
import imageio.v3 as iio
source, target = Path(sys.argv[1]), Path(sys.argv[2])
for name in ("images", "masks"):
    (target / f"{name}_16").mkdir(parents=True, exist_ok=True)
    for path in sorted((source / f"{name}_4").iterdir()):
        iio.imwrite(target / f"{name}_16" / path.name, iio.imread(path)[::4, ::4])
shutil.copy(source / "poses_bounds.npy", target)
PYTHON
    DATA=$SMOKE_DATA
else
    PY=python3
    say "installing $(ls .whl/*.whl | wc -l) wheels into /tmp/site"
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl 2>&1 | tee -a "$LOG"
    # the project needs lightning>=2.6 (Trainer.fit(weights_only=...)): the carried 2.6.6 only where the machine's is older
    if ! python3 -c "import lightning, sys; sys.exit(tuple(map(int, lightning.__version__.split('.')[:2])) < (2, 6))" 2>/dev/null; then
        say "the machine's lightning is missing or older than 2.6: installing the carried $(ls .whl/fallback/)"
        python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/fallback/lightning-*.whl 2>&1 | tee -a "$LOG"
    fi
    # the project from the working tree (python -m nerf_lightning.cli.train, ...: nerf-bench runs nerf-train and
    # nerf-eval so where their console scripts are not installed), with its version for the results' provenance
    export PYTHONPATH=/tmp/site:$REPO
    version=$(sed -n 's/^version = "\(.*\)"/\1/p' pyproject.toml)
    mkdir -p "/tmp/site/nerf_lightning-$version.dist-info"
    printf 'Metadata-Version: 2.1\nName: nerf-lightning\nVersion: %s\n' "$version" >"/tmp/site/nerf_lightning-$version.dist-info/METADATA"
fi
{
    echo "started $(date -u '+%Y-%m-%dT%H:%M:%SZ'); steps:$STEPS; deadline ${DEADLINE}s; $(nproc) CPU cores"
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>&1 | sed 's/^/nvidia-smi: /'
    $PY - <<'EOF' 2>&1
import platform, sys
import torch
print(f"python {platform.python_version()} ({sys.executable}); torch {torch.__version__}, CUDA {torch.version.cuda}, "
      f"cuda available {torch.cuda.is_available()}")
if torch.cuda.is_available():
    props = torch.cuda.get_device_properties(0)
    print(f"GPU: {torch.cuda.get_device_name(0)}, {props.total_memory / 2**30:.1f} GiB, sm_{props.major}{props.minor}, "
          f"{props.multi_processor_count} SMs")
from importlib.metadata import version, PackageNotFoundError
found = []
for name in ("lightning", "kornia", "kornia_rs", "hydra-core", "omegaconf", "numpy", "triton", "pytest", "pytest-xdist", "nerf-lightning"):
    try:
        found.append(f"{name} {version(name)}")
    except PackageNotFoundError:
        found.append(f"{name} -")
print("; ".join(found))
import kornia, hydra, omegaconf, nerf_lightning.training, nerf_lightning.bench.runner  # noqa: F401 (the imports a run needs)
print("imports ok")
EOF
} >"$WORK/env.txt" 2>&1
cat "$WORK/env.txt" | tee -a "$LOG"
SMI_PID=
if command -v nvidia-smi >/dev/null; then
    nvidia-smi --query-gpu=timestamp,utilization.gpu,memory.used --format=csv,noheader,nounits -lms 1000 >"$WORK/smi.csv" 2>/dev/null &
    SMI_PID=$!
fi

# ---- b. tests, f. host syncs (side by side: neither is timed) -------------------------------------------------------
# the whole suite, as the README runs it (its pyproject options: not the slow tests)
TESTS=(tests)
SYNC_STEPS=300 SYNC_WARMUP=256 SYNC_OVERRIDES=()
if [ "$SMOKE" = 1 ]; then
    TESTS=(tests/test_syncs.py tests/bench/test_figures.py tests/test_metrics.py)
    SYNC_STEPS=8 SYNC_WARMUP=4 SYNC_OVERRIDES=(data.scene.downscale=8 model.field.encoding.log2_table_size=14 model.sampler.grid.resolution=32 model.sampler.samples_per_step=16384
        model.sampler.density_pass_samples=65536 data.batch_size=256 model.sampler.grid.warmup_steps=4 model.sampler.grid.update_every=2)
fi
echo "$SYNC_WARMUP" >"$WORK/sync_warmup.txt"
# the files that touch a GPU run first, in a pass of their own: a suite cut at its time limit has run them (a lease
# of 2026-11-27 reached 306 of 757 tests in 2 minutes, none of these among them)
DEVICE_TESTS=(tests/test_devices_and_precision.py tests/test_syncs.py tests/splats tests/models tests/rendering
              tests/fields/test_hash_grid.py tests/fields/test_hash_grid_fast.py tests/bench/test_figures.py tests/data/test_batches.py)
run_tests() {
    local workers=() rest=()
    if [ "$SMOKE" != 1 ] && $PY -c "import xdist" 2>/dev/null; then workers=(-n "${GPU_CHECK_TEST_WORKERS:-14}"); fi
    local end=$(($(date +%s) + TEST_SECONDS))
    # SIGINT at the limit: pytest stops where it is and still writes its junit XML
    # (inductor's compile workers: a few a test worker, not one a core each; one CPU thread a worker, torch's and
    # numba's, since 14 workers each taking every core starve each other)
    if [ "$SMOKE" != 1 ]; then
        export OMP_NUM_THREADS=${GPU_CHECK_TEST_THREADS:-1} NUMBA_NUM_THREADS=${GPU_CHECK_TEST_THREADS:-1}
        TORCHINDUCTOR_COMPILE_THREADS=4 timeout -s INT -k 20 "$TEST_SECONDS" $PY -m pytest "${workers[@]}" -v -rfE --tb=short --durations=10 \
            --junitxml="$OUT/junit_device.xml" "${DEVICE_TESTS[@]}" >"$WORK/tests.log" 2>&1
        echo "pytest (device files) exit $?" >>"$WORK/tests.log"
        for path in "${DEVICE_TESTS[@]}"; do rest+=(--ignore="$path"); done
    fi
    local seconds=$((end - $(date +%s)))
    [ "$seconds" -gt 5 ] || { echo "no time left for the other tests" >>"$WORK/tests.log"; return; }
    TORCHINDUCTOR_COMPILE_THREADS=4 timeout -s INT -k 20 "$seconds" $PY -m pytest "${workers[@]}" -v -rfE --tb=short --durations=10 \
        --junitxml="$OUT/junit.xml" "${rest[@]}" "${TESTS[@]}" >>"$WORK/tests.log" 2>&1
    echo "pytest exit $?" >>"$WORK/tests.log"
}
run_syncs() {
    # as shipped (the preset's callbacks, progress bar, logger) but plain (a dispatch mode sees no op of a compiled
    # graph), past the grid's 256 warm-up steps so that its refreshes after warm-up are counted too; a stop after
    # training minutes so that syncs.json is written even if the steps are slow
    timeout -k 10 $((TEST_SECONDS + 20)) $PY -m nerf_lightning.cli.train experiment=fast_blender_gpu \
        data.root="$DATA/nerf_synthetic/lego" model.compile=false trainer.max_steps=$SYNC_STEPS data.val_every=null \
        "${SYNC_OVERRIDES[@]}" paths.output_dir="$WORK/syncs_run" \
        "+callbacks.syncs={_target_: nerf_lightning.training.syncs.CountHostSyncs, path: $OUT/syncs.json}" \
        "+callbacks.sync_stop={_target_: nerf_lightning.bench.callbacks.StopAtTrainingMinutes, minutes: $(awk "BEGIN{m = ($TEST_SECONDS - 25) / 60; print (m > 0.2) ? m : 0.2}")}" \
        >"$WORK/syncs.log" 2>&1
    echo "nerf-train (syncs) exit $?" >>"$WORK/syncs.log"
}
if wants tests || wants syncs; then
    t0=$(stamp)
    say "b/f: tests (${TEST_SECONDS}s at most: ${TESTS[*]}) beside the sync count ($SYNC_STEPS steps)"
    pids=()
    if wants tests; then run_tests & pids+=($!); fi
    if wants syncs; then run_syncs & pids+=($!); fi
    wait "${pids[@]}"
    phase "tests+syncs" "$t0"
    if wants tests; then say "---- tests"; tee -a "$LOG" <"$WORK/tests.log"; fi
    if wants syncs; then say "---- syncs run (its last 40 lines)"; tr '\r' '\n' <"$WORK/syncs.log" | grep -v '^\s*$' | tail -n 40 | tee -a "$LOG"; fi
fi

# ---- c, e, d: nerf-bench rows -----------------------------------------------------------------------------------
# bench NAME ROW_ID MINUTES SECONDS_BESIDES LEAST_MINUTES: the row trained MINUTES (fewer where the lease has less
# left, none under LEAST_MINUTES); SECONDS_BESIDES is the row's time besides training (start, the marks' scoring)
bench() {
    local name=$1 id=$2 minutes=$3 besides=$4 least=$5 suite=$SUITE
    local remaining; remaining=$(left)
    local fit; fit=$(awk "BEGIN{m = ($remaining - $besides) / 60; m = (m > $minutes) ? $minutes : int(m * 20) / 20; print m}")
    if [ "$SMOKE" = 1 ]; then fit=$(awk "BEGIN{print $minutes * 0.05}"); fi
    if awk "BEGIN{exit !($fit < $least)}" && [ "$SMOKE" != 1 ]; then
        cut "$name ($id) not run: ${remaining}s of the lease left, it needs $(awk "BEGIN{print $least * 60 + $besides}")s at least"
        return
    fi
    if [ "$SMOKE" = 1 ] || awk "BEGIN{exit !($fit < $minutes)}"; then
        suite=$WORK/suites/$name/gpu_check.yaml
        local scaled
        scaled=$($PY scripts/gpu_check_tools.py scale "$SUITE" "$id" "$fit" "$suite" $([ "$SMOKE" = 1 ] && echo --smoke)) || { cut "$name: could not write its suite"; return; }
        [ "$SMOKE" = 1 ] || cut "$name cut to $fit of $minutes minutes by the lease (${remaining}s left): row $scaled"
        id=$scaled
    fi
    local t0; t0=$(stamp)
    say "---- $name: nerf-bench run $suite --only $id (${remaining}s of the lease left)"
    local limit=$(($(left) - 5)); [ "$limit" -gt 10 ] || limit=10
    timeout -k 10 "$limit" $PY -m nerf_lightning.bench.runner run "$suite" --only "$id" --data-dir "$DATA" \
        --results "$WORK/results/$name" --report "$WORK/results/$name.md" --work "$WORK/bench/$name" --allow-dirty 2>&1 | tee -a "$LOG"
    say "$name: nerf-bench exit ${PIPESTATUS[0]}"
    phase "$name" "$t0"
    cp "$WORK/results/$name/"*.json "$OUT/$name.json" 2>/dev/null || say "$name: no results JSON"
    for log in "$WORK/bench/$name"/*/*/train.log "$WORK/bench/$name"/*/*/eval/*/eval.log; do
        [ -f "$log" ] || continue
        say "$name: ${log#"$WORK"/} (last 25 lines)"
        tr '\r' '\n' <"$log" | grep -v '^\s*$' | tail -n 25 | tee -a "$LOG"
    done
}
# a splat row's time besides training: its start (20 s) and two marks' scoring (25 s each on an H100, 2026-11-27)
wants splat && bench splat lego/splat_blender_gpu/2min/seed0 2 75 0.5
wants splatfox && bench splatfox fox/splat_360_gpu/2min/seed0 2 75 0.5
wants fast && bench fast lego/fast_blender_gpu/1min/seed0 1 60 0.5
wants cape && bench cape moldGoldCape/nerfacto_360_gpu/1min/seed0 1 45 0.5
# (its time besides training: the triangulation inside the masks too, 39 s on an H100's 16 cores, and two scorings,
# the second of which a lease of 2026-11-28 lost with 110 s allowed)
wants capesplat && bench capesplat moldGoldCape/splat_object_gpu/4min/seed0 4 150 1

# ---- summary --------------------------------------------------------------------------------------------------------
[ -n "$SMI_PID" ] && kill "$SMI_PID" 2>/dev/null
say "summary ($(left)s of the deadline left)"
$PY scripts/gpu_check_tools.py summary "$OUT" "$WORK" 2>&1 | tee -a "$LOG"
say "done"
