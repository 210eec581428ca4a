#!/usr/bin/env bash
# Prepares what benchmarks/gpu_checks.sh needs on a GPU machine that can neither install unicorn's dependencies nor
# generate the synthetic sets: no network (a cluster's offline GPU node), a stock PyTorch image without open3d (which
# generating a synthetic set needs; reading one does not). Run it from the repository root on a machine where this
# checkout is installed (pip install -e '.[dev]') and PyPI is reachable:
#   bash benchmarks/gpu_kit.sh [KIT [PYTHON]]     # defaults: gpu-kit, and the GPU machine's Python 3.12
# KIT then holds:
#   wheels/        the dependencies a PyTorch image may lack (hydra-core, omegaconf, antlr4, kornia, kornia-rs,
#                  trimesh, pykdtree; this machine's versions), for PYTHON on x86-64 Linux;
#   cache.tar.gz   the main job's synthetic set (UNICORN_CACHE of bm_train_rate.py);
#   testdata.tar.gz the test fixtures' synthetic sets (UNICORN_TEST_DATA, tests/support/prepared.py).
# Put KIT beside the checkout on the GPU machine (in its root, or name it in UNICORN_GPU_KIT): gpu_checks.sh then
# installs the wheels of the modules that machine cannot import, into a folder of its own, and unpacks the data.
set -euo pipefail
kit=${1:-gpu-kit}
py=${2:-3.12}
pure="hydra-core omegaconf antlr4-python3-runtime kornia trimesh"
binary="kornia_rs pykdtree"
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
if [ -e "$kit" ] && [ ! -d "$kit/wheels" ]; then
  echo "gpu_kit.sh: $kit exists and is not a kit of this script: name another folder" >&2
  exit 2
fi
rm -rf "$kit/wheels" "$kit/cache.tar.gz" "$kit/testdata.tar.gz"  # an earlier kit's
mkdir -p "$kit/wheels"

pinned() { python3 -c "import importlib.metadata as m, sys; print(*(f'{d}=={m.version(d)}' for d in sys.argv[1:]))" "$@"; }

echo "== wheels for Python $py"
# shellcheck disable=SC2046
python3 -m pip wheel -q --no-deps -w "$kit/wheels" $(pinned $pure)  # pure Python: any interpreter (antlr4 from its sdist)
# shellcheck disable=SC2046
python3 -m pip download -q --no-deps --only-binary=:all: --python-version "$py" --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
  --platform manylinux2014_x86_64 -d "$kit/wheels" $(pinned $binary)

echo "== the main job's synthetic set"
UNICORN_CACHE="$tmp/cache" OMP_NUM_THREADS=1 python3 -m unicorn.cli.train experiment=synthetic trainer.max_steps=1 \
  evaluate.enabled=false callbacks.images=null callbacks.heldout=null logger=none \
  trainer.enable_progress_bar=false "hydra.run.dir=$tmp/run" >"$tmp/train.log" 2>&1 \
  || { tail -20 "$tmp/train.log"; exit 1; }
tar -C "$tmp/cache" -czf "$kit/cache.tar.gz" .

echo "== the test fixtures' synthetic sets"
python3 -m tests.support.prepared "$tmp/testdata" >/dev/null
tar -C "$tmp/testdata" -czf "$kit/testdata.tar.gz" .

ls -l "$kit" "$kit/wheels"
du -sh "$kit"
