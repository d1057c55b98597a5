#!/usr/bin/env bash
# A kit for a GPU machine that has PyTorch but no network: the project's other dependencies that such images lack,
# installed for that machine's Python into one folder, with pybullet (only a source package on PyPI, so it is
# compiled here for that Python, 10-20 min on 2 cores) stripped to its one module (~8 MB).
#
#   benchmarks/offline_kit.sh [PYTHON_VERSION] [KIT_DIR]      # here, with network; defaults: 3.12 .gpu_kit
#
# There, from the repository root, with the machine's own python3 (which holds its CUDA PyTorch):
#
#   export PYTHONPATH=$PWD/.gpu_kit/site:$PWD
#   python3 -m benchmarks.gpu_check                             # then benchmarks/gpu_session.sh
#
# The versions are requirements.lock's. The kit is not in git (.gitignore); rebuild it when the lock changes.
set -euo pipefail

version=${1:-3.12}
kit=${2:-.gpu_kit}
python=${KIT_PYTHON:-python$version}  # KIT_PYTHON: that interpreter's path, where python3.12 is not on PATH
"$python" -c "import sys; assert sys.version.startswith('$version')" 2>/dev/null ||
    { echo "offline_kit: no Python $version as $python; set KIT_PYTHON=/path/to/python$version" >&2; exit 2; }
pin() { grep -i "^$1==" requirements.lock || { echo "offline_kit: $1 is not pinned in requirements.lock" >&2; exit 2; }; }

rm -rf "$kit" && mkdir -p "$kit/site"
# pure Python: the same files for any platform; the machine's image has the rest (numpy, h5py, scipy, ...)
"$python" -m pip install -q --no-deps --no-compile --target "$kit/site" \
    "$(pin hydra-core)" "$(pin omegaconf)" "$(pin antlr4-python3-runtime)" "$(pin gymnasium)" \
    "$(pin Farama-Notifications)"

build=$(mktemp -d)
trap 'rm -rf "$build"' EXIT
# built beside numpy, so that camera images come back as arrays (pybullet.isNumpyEnabled); numpy 2 modules import
# under any numpy 2 the machine has
"$python" -m venv "$build/env"
"$build/env/bin/pip" install -q "$(pin numpy)" setuptools wheel
"$build/env/bin/pip" wheel -q --no-cache-dir --no-deps --no-build-isolation --no-binary=:all: -w "$build" "$(pin pybullet)"
(cd "$build" && "$python" -m zipfile -e pybullet-*.whl unpacked)
module=$(find "$build/unpacked" -maxdepth 1 -name 'pybullet.cpython-*.so')
strip "$module"  # debug symbols are ~95 % of the module
cp "$module" "$kit/site/"
# what the machine's image has, here only to check that the kit imports
"$python" -m pip install -q --target "$build/image" numpy cloudpickle typing_extensions PyYAML packaging
PYTHONPATH="$kit/site:$build/image" "$python" -c "import pybullet, hydra, gymnasium, omegaconf
assert pybullet.isNumpyEnabled(), 'pybullet was built without numpy'
print('offline_kit: imports fine')"
du -sh "$kit"
