#!/usr/bin/env bash
# Paper scale on one GPU in at most 9 minutes (issue #17): installs the CUDA build of the jax
# version pyproject.toml pins, and the project, into .venv-gpu, then runs
# experiments/gpu/paper_scale.py (benchmark rows, a wall-budget phase-1 run, its evaluation and
# curves; see that file's docstring for the stages and their time limits).
#
#   bash experiments/gpu/paper_scale.sh [--dry-run] [--out DIR] [--budget SECONDS]
#                                       [--work DIR] [--skip STAGE ...] [--train-seconds S]
#
# Run from anywhere (it works in the repository root; relative paths are the caller's). OUT
# (--out, else $OUT, else ./gpu_out) receives summary.json, run.tar.gz, curves.png and this
# script's log, paper_scale.log. NMJAX_COMMIT=<hash> names the commit where the tree has no .git.
#
# Where no package registry can be reached (the lent H200 machines: nothing outside them can be),
# the pinned install cannot happen: the script then runs the project from src/ with the machine's
# own python3 and its CUDA jax, plus the wheels in .whl/ that experiments/gpu/fetch_wheels.sh
# downloads beforehand for the packages that image lacks; summary.json says which way it went
# and the versions that ran.
#
# --dry-run: no install (it prints the install command and checks the pin can be read), the
# same stages on the CPU at the tiny preset with $PYTHON (default python3); the tests run it.
set -uo pipefail

START=$(date +%s)
CALLER=$(pwd)
DRY=0
OUT_DIR="${OUT:-./gpu_out}"
BUDGET=""
PASS=()
while [ $# -gt 0 ]; do
    case "$1" in
        --dry-run) DRY=1 ;;
        --out) OUT_DIR="$2"; shift ;;
        --budget) BUDGET="$2"; PASS+=(--budget "$2"); shift ;;
        --work)
            case "$2" in /*) PASS+=(--work "$2") ;; *) PASS+=(--work "$CALLER/$2") ;; esac
            shift ;;
        *) PASS+=("$1") ;;
    esac
    shift
done
case "$OUT_DIR" in /*) ;; *) OUT_DIR="$CALLER/$OUT_DIR" ;; esac  # paths are the caller's
cd "$(dirname "$0")/../.." || exit 2
if [ -z "$BUDGET" ]; then
    if [ "$DRY" = 1 ]; then BUDGET=1800; else BUDGET=540; fi
fi
INSTALL_LIMIT=240  # seconds for the venv and every wheel, CUDA libraries included
VENV=.venv-gpu
mkdir -p "$OUT_DIR" || exit 2
LOG="$OUT_DIR/paper_scale.log"

main() {
    echo "paper_scale.sh: $(date -u +%Y-%m-%dT%H:%M:%SZ) dry_run=$DRY out=$OUT_DIR budget=${BUDGET}s"
    # The pin, e.g. "jax==0.10.2" in [project] dependencies: the CUDA plugin must match it.
    JAX_VERSION=$(sed -n 's/^[[:space:]]*"jax==\([^"]*\)".*/\1/p' pyproject.toml | head -n 1)
    if ! [[ "$JAX_VERSION" =~ ^[0-9]+(\.[0-9]+)+$ ]]; then
        echo "paper_scale.sh: cannot read the jax pin (a line \"jax==X.Y.Z\") from" \
            "pyproject.toml, got '$JAX_VERSION'; restore the pin or fix the pattern" >&2
        return 2
    fi
    echo "pinned jax: $JAX_VERSION"

    BASE_PY=""
    # 3.11 first: the version the pins were written and tested against.
    for candidate in python3.11 python3.12 python3.13 python3; do
        if command -v "$candidate" >/dev/null 2>&1 \
            && "$candidate" -c 'import sys; sys.exit(sys.version_info < (3, 11))' 2>/dev/null; then
            BASE_PY="$candidate"
            break
        fi
    done
    INSTALL_CMD="${BASE_PY:-python3} -m venv $VENV && $VENV/bin/python -m pip install uv &&"
    INSTALL_CMD="$INSTALL_CMD $VENV/bin/uv pip install --python $VENV/bin/python"
    INSTALL_CMD="$INSTALL_CMD 'jax[cuda12]==$JAX_VERSION' -e . (pip install where uv fails)"

    if [ "$DRY" = 1 ]; then
        echo "dry run: the install stage would run (limit ${INSTALL_LIMIT}s): $INSTALL_CMD"
        STATUS=dry-run
        SECONDS_TAKEN=0
        PY="${PYTHON:-python3}"
    else
        local tic=$(date +%s)
        STATUS=""
        if [ -z "$BASE_PY" ]; then
            echo "paper_scale.sh: no Python >= 3.11 on PATH (tried python3.11 .. python3)"
        elif ! timeout 30 "$BASE_PY" -m pip download --quiet --no-deps --no-cache-dir \
                --retries 0 --timeout 10 -d "$(mktemp -d)" "jax==$JAX_VERSION" >/dev/null 2>&1; then
            echo "paper_scale.sh: no package registry answers (pip download jax==$JAX_VERSION failed)"
        else
            echo "=== install (limit ${INSTALL_LIMIT}s): $INSTALL_CMD"
            # uv installs the large CUDA wheels several times faster than pip; pip is the fallback.
            timeout --kill-after=10 "$INSTALL_LIMIT" bash -c '
                set -e
                "$1" -m venv "$2"
                if "$2/bin/python" -m pip install --quiet --disable-pip-version-check uv; then
                    "$2/bin/uv" pip install --python "$2/bin/python" "jax[cuda12]==$3" -e . \
                        && exit 0
                    echo "uv failed; installing with pip"
                fi
                "$2/bin/python" -m pip install --quiet --disable-pip-version-check \
                    "jax[cuda12]==$3" -e .
            ' _ "$BASE_PY" "$VENV" "$JAX_VERSION"
            case $? in
                0) STATUS=ok ;;
                124|137) echo "=== install: timeout" ;;
                *) echo "=== install: failed" ;;
            esac
        fi
        PY="$VENV/bin/python"
        if [ -z "$STATUS" ]; then
            # No pinned install: the machine's python3 with its own jax, the project from src/.
            PY=python3
            export PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}"
            if compgen -G ".whl/*.whl" >/dev/null; then
                local site=/tmp/nmjax-gpu-site
                echo "installing the carried wheels into $site: $(cd .whl && echo *.whl)"
                python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir \
                    --upgrade --target "$site" .whl/*.whl && export PYTHONPATH="$site:$PYTHONPATH"
            fi
            if python3 -c 'import jax' 2>/dev/null; then
                STATUS="image (no pinned install: python3's own jax, src/ on PYTHONPATH)"
            else
                STATUS="failed (no pinned install, and python3 has no jax)"
            fi
        fi
        SECONDS_TAKEN=$(( $(date +%s) - tic ))
        echo "=== install: $STATUS after ${SECONDS_TAKEN}s"
    fi
    if [ "$DRY" = 1 ]; then PASS+=(--dry-run); fi
    local remain=$(( START + BUDGET - $(date +%s) ))
    [ "$remain" -gt 10 ] || remain=10
    # The Python side keeps its own deadline; this outer limit only catches it hanging.
    PYTHONUNBUFFERED=1 timeout --kill-after=15 $(( remain + 30 )) "$PY" \
        experiments/gpu/paper_scale.py --out "$OUT_DIR" --started-at "$START" \
        --install-status "$STATUS" --install-seconds "$SECONDS_TAKEN" \
        --install-command "$INSTALL_CMD" --jax-version "$JAX_VERSION" ${PASS[@]+"${PASS[@]}"}
}

main 2>&1 | tee -a "$LOG"
exit "${PIPESTATUS[0]}"
