# Sourced by the GPU scripts: run from the repository root, with the wheels of .whl/ (../shared/tools/gpu-wheels.sh,
# for a machine without a package index) installed under /tmp/site when present.
cd "$(dirname "${BASH_SOURCE[0]}")/.."
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD"
if [ -d .whl ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
  export PYTHONPATH="/tmp/site:$PWD"
fi
