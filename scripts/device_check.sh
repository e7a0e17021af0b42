#!/usr/bin/env bash
# One call on a lent GPU machine: install torchcbf from the working tree (no network), run
# the figures of scripts/device_figures.py, the tests that exercise the device, the
# benchmark scripts (torchcbf bench --quick) and scenario A, and write to $OUT:
#
#   device_check.json  every figure, the card's name, date, commit, versions, the test
#                      counts and failed ids, each step's exit status and seconds (rewritten
#                      after every step, so a run stopped at its limit still leaves one)
#   report.md          the same as Markdown tables (scripts/device_report.py)
#   install.log figures.log tests.log bench.log scenarios.log   the raw logs
#   profile.log        torch.profiler tables of the filter and the QP (scripts/device_profile.py),
#                      then the QP kernel's launch settings (scripts/device_kernels.py; also in
#                      the JSON) and Nsight Compute's sections of one launch where ncu runs
# (8 files: the device tool brings back at most 8)
#
# Steps, in order of value, each bounded by its own time budget (seconds, flags below):
#   install (120) -> figures (150, a figure started in time may run on up to 60 more)
#   -> tests (100) -> scenario A (45) -> scenario B (120) -> bench (160, shared by the
#   scripts) -> profile (60) -> kernels (120) -> ncu (60)
# about 16 minutes if every step runs to its budget (the JSON is kept up to date, so the
# call's limit loses only the step it stops); on an H200 the first six steps took 54, 79,
# 75 (8 test workers), 9, 61 and 41 s, so about 8.5 minutes with the bench's budget: the
# last two steps fit one 600 s call only with others skipped, so a session runs them in a
# second call (below), or in one call without the bench step (--skip bench --skip ncu:
# 324 s on an H200, the launch settings 45 s of it). A step that fails does not stop the others; the script ends with a
# list of the failed steps and exit status 1 if there is any.
#
# Right before the device call, HERE (the machine with the project's .venv; it records the commit):
#
#   bash scripts/device_check.sh --prepare
#
# copies the pure-Python packages the device image lacks (pytorch-mppi and its helpers,
# pytorch-kinematics, gymnasium, qpsolvers, qpth, cbfpy, qpax) from .venv, and unpacks
# CPython 3.12 wheels of proxsuite and clarabel (pip download) into build/device-carry/site and
# site-cp312 (used under Python 3.12 only), and records the
# commit in build/device-carry/commit.txt (the device gets no .git). build/ is git-ignored,
# so the run call must carry it. The device calls (what is under $OUT comes back even at the limit):
#
#   run(command="bash scripts/device_check.sh --skip kernels --skip ncu",
#       carry=["build/device-carry"], timeout_s=600)
#
# and, for the QP kernel's launch settings, a second call (about 3 minutes; the kernel runs
# from the tree, so no install):
#
#   run(command="bash scripts/device_check.sh --no-install --skip figures --skip tests
#       --skip scenarios --skip scenario_b --skip bench --skip profile",
#       carry=["build/device-carry"], timeout_s=300)
#
# Then: python scripts/device_report.py <files_at>/device_check.json --cpu <cpu json>.
# Rehearsal on a CPU (every step, small sizes): bash scripts/device_check.sh --device cpu
# --quick --out /tmp/device-check. Packages absent on the device and not carried (cvxpy)
# make their tests and benchmark lines skip.
#
# Flags: --device cuda|cpu (default cuda), --out DIR (default $OUT), --quick (small sizes),
# --python PY (default python3 on the device, .venv/bin/python here), --no-install,
# --figures-budget S, --tests-budget S, --bench-budget S, --scenario-budget S,
# --scenario-b-budget S, --profile-budget S, --kernels-budget S, --ncu-budget S,
# --skip STEP (figures|tests|bench|scenarios|profile|scenario_b|kernels|ncu; repeatable),
# --prepare.

set -uo pipefail

DEVICE=cuda
QUICK=0
INSTALL=1
PREPARE=0
FIGURES_BUDGET=150
TESTS_BUDGET=100
BENCH_BUDGET=160
SCENARIO_BUDGET=45
SCENARIO_B_BUDGET=120
PROFILE_BUDGET=60
KERNELS_BUDGET=120
NCU_BUDGET=60
SKIP=" "
PY=""
DEST="${OUT:-}"

die() { echo "device_check: $*" >&2; exit 2; }

while [ $# -gt 0 ]; do
    case "$1" in
        --device) DEVICE="$2"; shift 2 ;;
        --out) DEST="$2"; shift 2 ;;
        --quick) QUICK=1; shift ;;
        --python) PY="$2"; shift 2 ;;
        --no-install) INSTALL=0; shift ;;
        --prepare) PREPARE=1; shift ;;
        --figures-budget) FIGURES_BUDGET="$2"; shift 2 ;;
        --tests-budget) TESTS_BUDGET="$2"; shift 2 ;;
        --bench-budget) BENCH_BUDGET="$2"; shift 2 ;;
        --scenario-budget) SCENARIO_BUDGET="$2"; shift 2 ;;
        --scenario-b-budget) SCENARIO_B_BUDGET="$2"; shift 2 ;;
        --profile-budget) PROFILE_BUDGET="$2"; shift 2 ;;
        --kernels-budget) KERNELS_BUDGET="$2"; shift 2 ;;
        --ncu-budget) NCU_BUDGET="$2"; shift 2 ;;
        --skip) SKIP="$SKIP$2 "; shift 2 ;;
        -h|--help) sed -n '2,/^$/p' "$0"; exit 0 ;;
        *) die "unknown argument '$1' (see --help)" ;;
    esac
done

REPO="$(cd "$(dirname "$0")/.." && pwd)"
cd "$REPO" || die "cannot enter $REPO"
CARRY="$REPO/build/device-carry"

if [ "$PREPARE" = 1 ]; then
    PY="${PY:-$REPO/.venv/bin/python}"
    [ -x "$PY" ] || die "--prepare: no python at $PY (--python PY)"
    rm -rf "$CARRY" && mkdir -p "$CARRY/site" || die "cannot create $CARRY"
    for pkg in pytorch_mppi arm_pytorch_utilities pytorch_seed pytorch_kinematics gymnasium \
               farama_notifications qpsolvers qpth cbfpy qpax; do
        src="$("$PY" -c "import importlib.util as u, os; s = u.find_spec('$pkg'); \
print(os.path.dirname(s.origin) if s and s.origin else '')" 2>/dev/null)"
        [ -n "$src" ] && [ -d "$src" ] || die "--prepare: $pkg is not installed in $PY"
        cp -r "$src" "$CARRY/site/" || die "--prepare: copying $src failed"
    done
    # compiled peers and references the device image lacks: their CPython 3.12 wheels,
    # unpacked (proxsuite's from its cmeel prefix); without network here they skip there
    wheels="$(mktemp -d)"
    if "$PY" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 \
        --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 \
        --platform manylinux2014_x86_64 -d "$wheels" proxsuite==0.8.0 clarabel==0.11.1 \
        >/dev/null 2>&1; then
        for w in "$wheels"/*.whl; do
            "$PY" -m zipfile -e "$w" "$wheels/x" || die "--prepare: unpacking $w failed"
        done
        mkdir -p "$CARRY/site-cp312"
        cp -r "$wheels"/x/cmeel.prefix/lib/python3.12/site-packages/proxsuite "$wheels"/x/clarabel \
            "$CARRY/site-cp312/" || die "--prepare: copying the unpacked wheels failed"
    else
        echo "device_check: WARNING: no proxsuite/clarabel wheels (no network?); their lines will skip" >&2
    fi
    rm -rf "$wheels"
    find "$CARRY/site" -name __pycache__ -type d -prune -exec rm -rf {} +
    commit="$(git rev-parse HEAD)" || die "--prepare: not a git checkout"
    dirty=""; [ -n "$(git status --porcelain --untracked-files=no)" ] && dirty=" dirty"
    echo "$commit$dirty" >"$CARRY/commit.txt"
    echo "prepared $CARRY ($(du -sh "$CARRY" | cut -f1)), commit $commit$dirty"
    echo "device call 1: run(command=\"bash scripts/device_check.sh --skip kernels --skip ncu\", carry=[\"build/device-carry\"], timeout_s=600)"
    echo "device call 2: run(command=\"bash scripts/device_check.sh --no-install --skip figures --skip tests --skip scenarios --skip scenario_b --skip bench --skip profile\", carry=[\"build/device-carry\"], timeout_s=300)"
    exit 0
fi

[ -n "$DEST" ] || die "no output folder: set OUT or pass --out DIR"
case "$DEVICE" in cpu|cuda) ;; *) die "--device must be cpu or cuda, not '$DEVICE'" ;; esac
mkdir -p "$DEST" || die "cannot create $DEST"
DEST="$(cd "$DEST" && pwd)"
if [ -z "$PY" ]; then
    if [ -x "$REPO/.venv/bin/python" ]; then PY="$REPO/.venv/bin/python"; else PY=python3; fi
fi
command -v "$PY" >/dev/null || die "no python '$PY'"
export PYTHONUNBUFFERED=1 MPLBACKEND=Agg
# JAX peers (cbfpy, qpax) share the card with torch: no 75% preallocation
export XLA_PYTHON_CLIENT_PREALLOCATE=false
if [ -d "$CARRY/site" ]; then
    export PYTHONPATH="$CARRY/site${PYTHONPATH:+:$PYTHONPATH}"
    # the compiled wheels are CPython 3.12's: elsewhere (a rehearsal here) they would shadow
    # the installed packages and fail to import
    if [ -d "$CARRY/site-cp312" ] && "$PY" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 12))'; then
        export PYTHONPATH="$CARRY/site-cp312:$PYTHONPATH"
    fi
elif [ "$DEVICE" = cuda ]; then
    echo "device_check: WARNING: $CARRY/site is missing (run --prepare here and carry" \
         "build/device-carry): pytorch-mppi, arm and gymnasium tests and lines will skip" >&2
fi
WORK="$(mktemp -d)"  # figures.json, tests.xml, steps.tsv: the JSON's pieces
STEPS="$WORK/steps.tsv"
: >"$STEPS"
FAILED=""

# step NAME RC SECONDS NOTE: one line of the step table, then the JSON so far
step() {
    printf '%s\t%s\t%s\t%s\n' "$1" "$2" "$3" "$4" >>"$STEPS"
    if [ "$2" != 0 ]; then FAILED="$FAILED $1"; echo "device_check: step $1 FAILED (exit $2): $4" >&2; fi
    "$PY" scripts/device_report.py --collect "$WORK" "$DEST/device_check.json" \
        || echo "device_check: writing device_check.json failed" >&2
}
skipped() { case "$SKIP" in *" $1 "*) return 0 ;; *) return 1 ;; esac; }
now() { date +%s.%N; }
since() { awk -v a="$1" -v b="$(now)" 'BEGIN { printf "%.1f", b - a }'; }

# --- the device and torch, before anything else -------------------------------------------
"$PY" - "$DEVICE" <<'EOF' || die "torch does not import or does not see the device (above)"
import sys
import torch
device = sys.argv[1]
print(f"python {sys.version.split()[0]}, torch {torch.__version__}, cuda {torch.version.cuda}")
if device == "cuda":
    if not torch.cuda.is_available():
        sys.exit("--device cuda, but torch.cuda.is_available() is False")
    print("card:", torch.cuda.get_device_name(0))
EOF
command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.sm \
    --format=csv >"$DEST/install.log" 2>&1

# --- install ------------------------------------------------------------------------------
t0=$(now)
if [ "$INSTALL" = 1 ]; then
    timeout 120 "$PY" -m pip install --no-deps --no-build-isolation --no-index -e . \
        >>"$DEST/install.log" 2>&1
    rc=$?
    if [ "$rc" = 0 ]; then
        step install 0 "$(since "$t0")" "pip install -e . (no deps, no index)"
    elif [ "$rc" = 124 ]; then
        # the build itself is slow here: a second build would be too
        step install 1 "$(since "$t0")" "pip install -e . stopped after 120 s (install.log); running from PYTHONPATH with whatever C kernels it built"
    else
        # an older setuptools rejects pyproject.toml's metadata: build the C kernels (CPU
        # only) in place from setup.py alone, in a folder without pyproject.toml whose
        # torchcbf/ is the tree's; the package itself runs from the tree
        tmpb="$(mktemp -d)"
        ln -s "$REPO/torchcbf" "$tmpb/torchcbf" && cp setup.py "$tmpb/"
        (cd "$tmpb" && timeout 120 "$PY" setup.py build_ext --inplace) >>"$DEST/install.log" 2>&1
        rc=$?
        rm -rf "$tmpb"
        step install 1 "$(since "$t0")" "pip install -e . failed (install.log); C kernels by setup.py build_ext --inplace: exit $rc; running from PYTHONPATH"
    fi
else
    step install 0 0 "skipped (--no-install); running from PYTHONPATH"
fi
# the working tree comes first on sys.path, whatever was installed before
export PYTHONPATH="$REPO${PYTHONPATH:+:$PYTHONPATH}"
"$PY" -c "import torchcbf, torchcbf.cli; print('torchcbf', torchcbf.__version__, 'from', torchcbf.__file__)" \
    >>"$DEST/install.log" 2>&1 || { cat "$DEST/install.log" >&2; die "torchcbf does not import"; }
"$PY" -m torchcbf.cli info >>"$DEST/install.log" 2>&1
tail -n 3 "$DEST/install.log"

# --- figures ------------------------------------------------------------------------------
if ! skipped figures; then
    t0=$(now)
    quick=(); [ "$QUICK" = 1 ] && quick=(--quick)
    timeout -k 10 $((FIGURES_BUDGET + 60)) "$PY" scripts/device_figures.py --device "$DEVICE" \
        "${quick[@]}" --budget "$FIGURES_BUDGET" --out "$WORK/figures.json" 2>&1 | tee "$DEST/figures.log"
    step figures "${PIPESTATUS[0]}" "$(since "$t0")" "scripts/device_figures.py (figures.log)"
fi

# --- tests on the device --------------------------------------------------------------------
if ! skipped tests; then
    t0=$(now)
    par=()
    if [ "$DEVICE" = cuda ] && "$PY" -c "import xdist" 2>/dev/null; then par=(-n 8); fi
    # SIGINT at the budget: pytest stops and still writes the JUnit file of what ran
    TORCHCBF_TEST_DEVICES="$DEVICE" timeout -s INT -k 30 "$TESTS_BUDGET" "$PY" -m pytest \
        -m "device and not slow" -q -p no:cacheprovider "${par[@]}" --durations=15 \
        --junitxml="$WORK/tests.xml" >"$DEST/tests.log" 2>&1
    rc=$?
    tail -n 5 "$DEST/tests.log"
    note="TORCHCBF_TEST_DEVICES=$DEVICE pytest -m 'device and not slow' (tests.log)"
    [ "$rc" = 124 ] || [ "$rc" = 130 ] || [ "$rc" = 2 ] && note="$note; stopped at the budget or interrupted"
    step tests "$rc" "$(since "$t0")" "$note"
fi

# --- scenario A ----------------------------------------------------------------------------
if ! skipped scenarios; then
    t0=$(now)
    if [ "$QUICK" = 1 ]; then size=(--seeds 2 --samples 500); else size=(--seeds 10 --samples 10000); fi
    tmp="$(mktemp -d)"
    timeout -s INT -k 10 "$SCENARIO_BUDGET" "$PY" -m torchcbf.cli reach-avoid "${size[@]}" \
        --device "$DEVICE" --out "$tmp/reach-avoid" --no-gif --no-progress >"$DEST/scenarios.log" 2>&1
    rc=$?
    cp "$tmp/reach-avoid/metrics.json" "$WORK/scenario_a.json" 2>/dev/null
    step scenario_a "$rc" "$(since "$t0")" "torchcbf reach-avoid ${size[*]} --device $DEVICE --no-gif (wall seconds: start, run and figures)"
    rm -rf "$tmp"
fi

# --- scenario B at the paper's size -----------------------------------------------------------
if ! skipped scenario_b; then
    t0=$(now)
    if [ "$QUICK" = 1 ]; then size=(--seeds 2 --samples 500); else size=(--seeds 32 --samples 20000); fi
    tmp="$(mktemp -d)"
    timeout -s INT -k 10 "$SCENARIO_B_BUDGET" "$PY" -m torchcbf.cli mppi-cbf "${size[@]}" \
        --device "$DEVICE" --out "$tmp/mppi-cbf" --no-gif --no-progress >>"$DEST/scenarios.log" 2>&1
    rc=$?
    cp "$tmp/mppi-cbf/metrics.json" "$WORK/scenario_b.json" 2>/dev/null
    step scenario_b "$rc" "$(since "$t0")" "torchcbf mppi-cbf ${size[*]} --device $DEVICE --no-gif (wall seconds: start, run and figures; all five methods)"
    rm -rf "$tmp"
fi

# --- benchmark scripts ------------------------------------------------------------------------
if ! skipped bench; then
    # one script at a time, each with its share of the budget, so that one slow script does
    # not starve the others (the share is in bench.log)
    : >"$DEST/bench.log"
    names="$("$PY" -m torchcbf.cli bench --list | awk '{print $1}')"
    count="$(echo "$names" | wc -w)"
    [ "$count" -gt 0 ] || step bench 1 0 "torchcbf bench --list found no scripts"
    for name in $names; do
        t0=$(now)
        share=$((BENCH_BUDGET / count))
        echo "### torchcbf bench --only $name --device $DEVICE --quick (budget ${share} s)" >>"$DEST/bench.log"
        timeout -s INT -k 10 "$share" "$PY" -m torchcbf.cli bench --only "$name" --device "$DEVICE" \
            --quick >>"$DEST/bench.log" 2>&1
        rc=$?
        note="torchcbf bench --only $name --device $DEVICE --quick (bench.log)"
        [ "$rc" = 124 ] && note="$note: stopped at its ${share} s budget"
        step "bench_$name" "$rc" "$(since "$t0")" "$note"
    done
fi

# --- where the filter's and the QP's time goes (torch.profiler tables) ------------------------
if ! skipped profile; then
    t0=$(now)
    states=1000000; [ "$QUICK" = 1 ] && states=2000
    timeout -s INT -k 10 "$PROFILE_BUDGET" "$PY" scripts/device_profile.py --device "$DEVICE" \
        --states "$states" --out "$DEST/profile.log" >/dev/null 2>"$WORK/profile.err"
    rc=$?
    [ "$rc" = 0 ] || cat "$WORK/profile.err" >>"$DEST/scenarios.log"
    step profile "$rc" "$(since "$t0")" "scripts/device_profile.py --states $states (profile.log)"
fi

# --- the QP kernel's launch settings, timed (appended to profile.log) -----------------------
if ! skipped kernels; then
    t0=$(now)
    if [ "$QUICK" = 1 ]; then size=(--states 64 --reps 1 --settings 32x1 16x1); else size=(--states 1000000 --compile-jobs 8); fi
    if [ "$DEVICE" = cuda ] || [ "${TRITON_INTERPRET:-0}" = 1 ]; then
        echo "## QP kernel launch settings (scripts/device_kernels.py ${size[*]})" >>"$DEST/profile.log"
        timeout -s INT -k 10 "$KERNELS_BUDGET" "$PY" scripts/device_kernels.py --device "$DEVICE" \
            "${size[@]}" --out "$WORK/kernels.json" >>"$DEST/profile.log" 2>&1
        step kernels "$?" "$(since "$t0")" "scripts/device_kernels.py ${size[*]} (profile.log, JSON)"
    else
        step kernels 0 0 "skipped: the kernel runs on the CPU only under TRITON_INTERPRET=1"
    fi
fi

# --- Nsight Compute's view of one launch of the QP kernel (appended to profile.log) ---------
if ! skipped ncu; then
    t0=$(now)
    if [ "$DEVICE" = cuda ] && command -v ncu >/dev/null; then
        echo "## ncu: one launch of the QP kernel, the filter's QP on 200000 states, float32" >>"$DEST/profile.log"
        # the clocks as they are (the device tool's rule); the second launch (after a warm-up)
        timeout -s INT -k 10 "$NCU_BUDGET" ncu --clock-control none \
            --kernel-name regex:_dual_solve_kernel --launch-skip 1 --launch-count 1 \
            --section SpeedOfLight --section Occupancy --section LaunchStats \
            --section WarpStateStats --section SchedulerStats --section ComputeWorkloadAnalysis \
            "$PY" scripts/device_kernels.py --device cuda --states 200000 --reps 1 \
            --dtypes float32 --settings 32x1 >>"$DEST/profile.log" 2>&1
        step ncu "$?" "$(since "$t0")" "ncu sections of the QP kernel (profile.log)"
    else
        step ncu 0 0 "skipped: no ncu here (or not on CUDA)"
    fi
fi

# --- the JSON and the report ---------------------------------------------------------------
"$PY" scripts/device_report.py --collect "$WORK" "$DEST/device_check.json" \
    || die "writing device_check.json failed"
"$PY" scripts/device_report.py "$DEST/device_check.json" --out "$DEST/report.md" \
    || die "scripts/device_report.py failed"
rm -rf "$WORK"
cat "$DEST/report.md"
if [ -n "$FAILED" ]; then
    echo "device_check: FAILED steps:$FAILED (logs in $DEST)" >&2
    exit 1
fi
echo "device_check: all steps passed; $DEST/device_check.json"
