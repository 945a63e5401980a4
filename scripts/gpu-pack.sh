#!/usr/bin/env bash
# Packs what the lent GPU machine lacks into gpu-env.tar.xz (gitignored), for a session's device
# runs to carry (`carry = ["gpu-env.tar.xz"]`; at most 64 MiB travel): that machine reaches no
# package registry and its python3 (3.12, /opt/torch/.venv) already has torch, numpy, scipy,
# scikit-learn, onnxruntime, matplotlib, h5py, pyarrow and pandas (docs/tutorials/gpu-machine.md).
#
#   bash scripts/gpu-pack.sh            # here, after scripts/setup.sh
#   bash scripts/gpu-check.sh           # there: unpacks it and checks the machine
#
# It holds, installed for CPython $GPU_PYTHON (default 3.12) on manylinux x86_64 with
# `pip install --target --no-deps`: Mitsuba, Dr.Jit, Sionna RT and Sionna SYS at this
# checkout's versions, importlib_resources and nvidia-ml-py; this checkout's caviar (the
# abi3 wheel maturin builds) and caviar-plugins (with their entry points, through which
# plugins are found); pymavlink with its `all` dialect only (live-uav); and the three named
# stand-ins of scripts/gpu-standins for the notebook packages Sionna RT imports only for its
# previewer (ipywidgets, pythreejs, IPython), which the GPU machine lacks. To fit,
# the Mitsuba variants other than CUDA's mono-polarized (Sionna's) and RGB (the camera's) and
# Sionna RT's large example scenes are left out. SUMO cannot travel (its wheels are 148 and
# 86 MB): the SUMO blueprints replay recorded traffic there. ns-3 cannot travel either: the `ns3`
# wheel alone (3.44, cp312) is 69 MB packed and 283 MB unpacked, and it needs cppyy's Cling
# besides, over the 64 MiB that travel; sar-ns3 is reported as skipped there.
set -euo pipefail
cd "$(dirname "$0")/.."
py=.venv/bin/python
pyver="${GPU_PYTHON:-3.12}"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
site="$work/site"
mkdir -p "$site" "$work/wheels"

version() { "$py" -c "from importlib.metadata import version; print(version('$1'))"; }
echo "== wheels for CPython $pyver"
"$py" -m pip install --quiet --target "$site" --no-deps --python-version "$pyver" \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
  --only-binary=:all: \
  "mitsuba==$(version mitsuba)" "drjit==$(version drjit)" "sionna-rt==$(version sionna-rt)" \
  "sionna-no-rt==$(version sionna-no-rt)" "importlib_resources" "nvidia-ml-py" \
  "pymavlink==$(version pymavlink)" "fastcrc==$(version fastcrc)"

echo "== caviar (abi3) and caviar-plugins"
.venv/bin/maturin build --release --quiet --out "$work/wheels" > /dev/null
"$py" -m pip wheel --quiet --no-deps --wheel-dir "$work/wheels" ./plugins
rm -rf plugins/build  # (setuptools builds in the tree)
"$py" -m pip install --quiet --target "$site" --no-deps "$work"/wheels/*.whl

echo "== stand-ins for the notebook packages (Sionna RT's previewer only; scripts/gpu-standins)"
cp -r scripts/gpu-standins/ipywidgets scripts/gpu-standins/pythreejs scripts/gpu-standins/IPython "$site/"

echo "== trimming"
find "$site/mitsuba" -maxdepth 1 \( -name 'llvm_*' -o -name 'scalar_*' -o -name 'cuda_ad_spectral*' \
  -o -name 'cuda_*spectral*' \) -exec rm -rf {} +
find "$site/mitsuba" -maxdepth 1 -name 'cuda_ad_mono*' ! -name 'cuda_ad_mono_polarized*' -exec rm -rf {} +
rm -rf "$site/mitsuba/include" "$site/mitsuba/cmake" "$site/drjit/include" "$site/drjit/cmake"
for scene in munich florence san_francisco etoile; do
  rm -rf "$site/sionna/rt/scenes/$scene"
done
# pymavlink (live-uav): the `all` MAVLink 2 dialect only (it parses MAVLink 1 too), 48 MB -> 3 MB.
find "$site/pymavlink/dialects/v20" -maxdepth 1 -name '*.py' ! -name 'all.py' ! -name '__init__.py' -delete
rm -rf "$site/pymavlink/dialects/v10" "$site/pymavlink/generator/C" "$site/pymavlink/generator/java" \
  "$site/pymavlink/message_definitions"
find "$site" -name '__pycache__' -type d -prune -exec rm -rf {} +

echo "== packing"
tar -C "$work" -cf - site | xz -9 -T0 > gpu-env.tar.xz
size=$(stat -c %s gpu-env.tar.xz)
echo "gpu-env.tar.xz: $((size / 1024 / 1024)) MiB ($(du -sh "$site" | cut -f1) unpacked)"
if [ "$size" -gt $((60 * 1024 * 1024)) ]; then
  echo "error: over 60 MiB: it would not travel with the working tree (64 MiB in all)" >&2
  exit 1
fi
