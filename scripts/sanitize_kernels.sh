#!/usr/bin/env bash
# Build the four C kernels with AddressSanitizer and UndefinedBehaviorSanitizer into a
# temporary copy of the package (the installed libraries are left alone), then run the
# kernel tests and the kernel fuzz (scripts/fuzz_kernels.py) against those builds.
#
# Usage, from the repository root:
#     scripts/sanitize_kernels.sh [extra pytest arguments]
# Environment: PYTHON (default .venv/bin/python, else python3), CC (default gcc),
# FUZZ_CASES (cases per family for the fuzz, default 40), REV (a commit: sanitize its package
# and kernels instead of the working tree's), KEEP_TMP=1 keeps the build.
#
# Exit status: 0 when the tests and the fuzz pass with no sanitizer report, else non-zero
# (every sanitizer report aborts the process that triggered it).
set -euo pipefail

ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$ROOT"
PY=${PYTHON:-}
if [[ -z $PY ]]; then
    if [[ -x .venv/bin/python ]]; then PY=.venv/bin/python; else PY=python3; fi
fi
PY=$(command -v "$PY")
PY="$(cd "$(dirname "$PY")" && pwd)/$(basename "$PY")"  # absolute, the venv's link kept
CC=${CC:-gcc}

TMP=$(mktemp -d "${TMPDIR:-/tmp}/torchcbf-sanitize.XXXXXX")
if [[ ${KEEP_TMP:-0} != 1 ]]; then trap 'rm -rf "$TMP"' EXIT; fi
LOGS="$TMP/logs"
mkdir -p "$LOGS" "$TMP/pkg"

# the package's Python files (the loader looks for each library next to its module): the
# working tree's, or those of the commit REV names (tests and fuzz: the working tree's)
if [[ -n ${REV:-} ]]; then
    git archive "$REV" torchcbf | tar -x -C "$TMP/pkg"
else
    cp -r torchcbf "$TMP/pkg/torchcbf"
fi
find "$TMP/pkg/torchcbf" \( -name '*.so' -o -name '__pycache__' \) -prune -exec rm -rf {} +

SUFFIX=$("$PY" -c 'import importlib.machinery as m; print(m.EXTENSION_SUFFIXES[0])')
# the flags setuptools compiles with (Python's CFLAGS and CCSHARED: -DNDEBUG, -fwrapv, ...),
# without their optimisation level; then the extension's own flags from setup.py, with the
# sanitizers' -O1 last so it wins over setup.py's -O3
read -r -a BASE <<<"$("$PY" -c '
import sysconfig as s
flags = (s.get_config_var("CFLAGS") or "").split() + (s.get_config_var("CCSHARED") or "").split()
print(" ".join(f for f in flags if not f.startswith("-O")))
')"
SAN=(-fsanitize=address,undefined -fsanitize=float-cast-overflow -fno-omit-frame-pointer -g -O1)
MVEC=$("$PY" -c '
import platform, sys
print(int(sys.platform.startswith("linux") and platform.machine() in ("x86_64", "AMD64")))
')

build() {  # build <module path> <extra cflags (one word)> <libraries> <sources...>
    local module=$1 extra=$2 libs=$3
    shift 3
    local out="$TMP/pkg/${module//.//}$SUFFIX"
    local -a extra_flags=() lib_flags=()
    [[ -n $extra ]] && read -r -a extra_flags <<<"$extra"
    for l in $libs; do lib_flags+=("-l$l"); done
    echo "build $module"
    "$CC" "${BASE[@]}" -std=c99 "${extra_flags[@]}" "${SAN[@]}" -shared "${@/#/$TMP/pkg/}" \
        -o "$out" \
        "${lib_flags[@]}"
}

ROLLOUT_LIBS="m"
[[ $MVEC == 1 ]] && ROLLOUT_LIBS="mvec m"
build torchcbf.qp._dual_kernel "" "" torchcbf/qp/_dual_kernel.c
build torchcbf.barriers._lie_kernel "" "m" torchcbf/barriers/_lie_kernel.c
build torchcbf.filters._filter_kernel "" "m" \
    torchcbf/filters/_filter_kernel.c torchcbf/qp/_dual_kernel.c
build torchcbf.mppi._rollout_kernel "-fno-math-errno" "$ROLLOUT_LIBS" \
    torchcbf/mppi/_rollout_kernel.c

ASAN_LIB=$("$CC" -print-file-name=libasan.so)
UBSAN_LIB=$("$CC" -print-file-name=libubsan.so)
for lib in "$ASAN_LIB" "$UBSAN_LIB"; do
    [[ -e $lib ]] || { echo "sanitize_kernels: $lib not found (install the gcc runtimes)"; exit 2; }
done
export LD_PRELOAD="$ASAN_LIB:$UBSAN_LIB${LD_PRELOAD:+:$LD_PRELOAD}"
export ASAN_OPTIONS="detect_leaks=0:abort_on_error=1:halt_on_error=1:log_path=$LOGS/asan"
export UBSAN_OPTIONS="halt_on_error=1:abort_on_error=1:print_stacktrace=1:log_path=$LOGS/ubsan"
export PYTHONPATH="$TMP/pkg${PYTHONPATH:+:$PYTHONPATH}"
export PYTHONDONTWRITEBYTECODE=1
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-2}

# the sanitized libraries must be the ones that load, and load at their version (run from
# $TMP: `python -` puts the working directory first on sys.path)
(cd "$TMP" && "$PY" - "$TMP/pkg") <<'EOF'
import sys
from pathlib import Path

import torchcbf
from torchcbf.barriers import native
from torchcbf.filters import realtime
from torchcbf.mppi import _rollout
from torchcbf.qp import _dual_native

root = Path(sys.argv[1]).resolve()
assert Path(torchcbf.__file__).resolve().is_relative_to(root), torchcbf.__file__
for name, mod in [("qp", _dual_native), ("lie", native), ("filter", realtime), ("mppi", _rollout)]:
    lib = mod._library()
    assert lib is not None, f"the sanitized {name} kernel does not load"
    assert Path(lib._name).resolve().is_relative_to(root), lib._name
print("sanitized kernels load from", root)
EOF

status=0
TESTS=()
for t in tests/test_native.py tests/qp/test_dual_native.py tests/barriers/test_native_terms.py \
    tests/filters/test_realtime.py tests/mppi/test_rollout_kernel.py tests/test_kernel_fuzz.py \
    tests/test_changed_between_calls.py; do
    [[ -e $t ]] && TESTS+=("$t")
done
# the pytest script, not `python -m pytest`: the latter puts the working directory (and the
# uninstrumented package in it) first on sys.path
PYTEST="$(dirname "$PY")/pytest"
[[ -x $PYTEST ]] || PYTEST="$PY -m pytest --rootdir=$ROOT"
# glibc's heap thresholds mean nothing under ASan's allocator
SKIP=(--deselect tests/test_native.py::test_freed_blocks_are_reused_without_page_faults)
echo "pytest ${TESTS[*]}"
(cd "$ROOT" && $PYTEST -q -p no:cacheprovider "${SKIP[@]}" "${TESTS[@]}" "$@") || status=$?
echo "pytest exit status: $status"

fuzz_status=0
(cd "$TMP" && "$PY" "$ROOT/scripts/fuzz_kernels.py" --cases "${FUZZ_CASES:-40}") ||
    fuzz_status=$?
echo "fuzz exit status: $fuzz_status"

reports=0
for f in "$LOGS"/asan.* "$LOGS"/ubsan.*; do
    [[ -e $f ]] || continue
    reports=$((reports + 1))
    echo "==== sanitizer report $f"
    cat "$f"
done
echo "sanitize_kernels: $reports sanitizer report(s), pytest $status, fuzz $fuzz_status"
if ((reports > 0 || status != 0 || fuzz_status != 0)); then
    exit 1
fi
