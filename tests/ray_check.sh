#!/usr/bin/env bash
# The Ray launcher check, in an environment of its own: hydra-ray-launcher needs cloudpickle<3, and joblib 1.6
# needs cloudpickle>=3, so the Ray environment keeps joblib<1.6 (the `ray` extra of pyproject.toml pins both).
# It runs the Ray launcher's tests, which the main suite skips because the main environment has no Ray launcher:
# `auto` refused at plan time where it finds no Ray instance, a sweep on a local Ray instance, and the Ray commands
# of docs/clusters.md run as written, on a local instance and on a two-node Ray cluster started from this venv's
# `ray` (tests/clusters/ray_cluster.py; about a minute).
# Usage: bash tests/ray_check.sh        (RAY_VENV=DIR to choose where the venv lives; it is reused when present)
#        bash tests/ray_check.sh --install   (builds the venv and stops: .ci/run builds it while the main suite runs)
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
RAY_VENV=${RAY_VENV:-${TMPDIR:-/tmp}/riskplan-ray-venv}
if [ ! -x "$RAY_VENV/bin/python" ]; then
  "$PY" -m venv "$RAY_VENV"
  "$RAY_VENV/bin/python" -m pip install -q --upgrade pip
fi
"$RAY_VENV/bin/python" -m pip install -q -e '.[ray]' "pytest>=8"
[ "${1:-}" = --install ] && exit 0
"$RAY_VENV/bin/python" -c "import hydra_plugins.hydra_ray_launcher, ray, cloudpickle, joblib; \
print(f'ray {ray.__version__}, cloudpickle {cloudpickle.__version__}, joblib {joblib.__version__}')"
export RAY_USAGE_STATS_ENABLED=0
# Ray keeps its sessions' logs and sockets in the temporary folder, and its killed helpers leave theirs: the tests'
# instances get a folder of their own, removed at the end.
TMPDIR=$(mktemp -d "${TMPDIR:-/tmp}/riskplan-ray-check-XXXXXX")
export TMPDIR
trap 'rm -rf "$TMPDIR"' EXIT
# test_ray_bad_settings.py first: `auto` finding no Ray instance needs a machine where no test's Ray is running
"$RAY_VENV/bin/python" -m pytest -q -p no:cacheprovider tests/clusters/test_ray_bad_settings.py \
  tests/experiments/sweeping/test_ray_launcher.py tests/clusters/test_ray_sweeps.py
