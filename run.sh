#!/usr/bin/env bash
# One entry point for newcomers and CI: sets up .venv when needed, then runs a job.
#   ./run.sh demo    the CSO demo pipeline on MetaWorld (configs/metaworld_demo.yaml)
#   ./run.sh test    ruff + the whole test suite
#   ./run.sh CMD...  any command inside the project's venv (e.g. ./run.sh lerobot-train --help)
set -euo pipefail
cd "$(dirname "$0")"
VENV=.venv

find_python() {
    local c
    # LeRobot 0.6.1 is tested on 3.12: prefer it, then any newer Python.
    for c in python3.12 python3 python3.13 python; do
        if command -v "$c" >/dev/null 2>&1 && "$c" -c 'import sys; sys.exit(sys.version_info < (3, 12))' 2>/dev/null; then
            command -v "$c"; return 0
        fi
    done
    if command -v pyenv >/dev/null 2>&1; then
        local root v
        root=$(pyenv root)
        for v in $(ls -1 "$root/versions" 2>/dev/null | grep '^3\.12\.'; ls -1 "$root/versions" 2>/dev/null | sort -rV); do
            c="$root/versions/$v/bin/python"
            if [ -x "$c" ] && "$c" -c 'import sys; sys.exit(sys.version_info < (3, 12))' 2>/dev/null; then
                echo "$c"; return 0
            fi
        done
    fi
    return 1
}

setup() {
    local stamp="$VENV/.installed" want
    want=$(cat pyproject.toml hardware/pyproject.toml | sha256sum | cut -d' ' -f1)
    if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then return 0; fi
    if [ ! -x "$VENV/bin/python" ]; then
        local py
        py=$(find_python) || { echo "error: Python >= 3.12 not found on PATH or under pyenv; install Python 3.12+ first" >&2; exit 1; }
        echo "[setup] creating $VENV with $py" >&2
        "$py" -m venv "$VENV"
    fi
    echo "[setup] installing lerobot_policy_cso (with LIBERO and its assets) and lerobot_robot_piper (first time: a few minutes)" >&2
    "$VENV/bin/python" -m pip install -q --upgrade pip >&2
    "$VENV/bin/python" -m pip install -q -e "./hardware[lerobot,twin]" -e ".[test,libero]" >&2
    echo "$want" > "$stamp"
}

setup
export PATH="$PWD/$VENV/bin:$PATH"
export HF_HUB_OFFLINE=1 HF_DATASETS_OFFLINE=1 TOKENIZERS_PARALLELISM=false
cmd=${1:-help}
case "$cmd" in
    demo)
        shift
        exec lerobot-cso pipeline --config_path=configs/metaworld_demo.yaml "$@" ;;
    test)
        shift
        # The pynput keyboard test needs an X server: Xvfb from the system's packages, where this user may
        # install them (elsewhere that one test is skipped, saying why).
        if ! command -v Xvfb >/dev/null 2>&1 && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
            echo "[setup] installing xvfb (an X server for the pynput keyboard test)" >&2
            apt-get install -y -q xvfb >/dev/null 2>&1 || (apt-get update -q >/dev/null 2>&1 \
                && apt-get install -y -q xvfb >/dev/null 2>&1) || echo "[setup] xvfb could not be installed" >&2
        fi
        ruff check .
        # One worker per core, one torch thread each; a test module stays on one worker, so its module-scoped
        # fixtures are built once.
        OMP_NUM_THREADS=1 exec python -m pytest -q -n auto --dist loadfile "$@" ;;
    help|-h|--help)
        sed -n 2,5p "$0" ;;
    *)
        exec "$@" ;;
esac
