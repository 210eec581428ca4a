# Sourced from the repository root (`source benchmarks/gpu_env.sh`, as gpu_checks.sh does): sets this shell up to run
# unicorn's tests and benchmarks from the checkout with a kit made by benchmarks/gpu_kit.sh, where one lies
# (UNICORN_GPU_KIT, default ./gpu-kit). The wheels of the modules this machine cannot import are installed into a
# folder of their own (nothing else is touched), the synthetic sets are unpacked beside it, and PYTHONPATH,
# UNICORN_CACHE and UNICORN_TEST_DATA point at them: nothing then needs the network or open3d. Without a kit it
# changes nothing. Returns non-zero where the kit cannot be installed.
kit=${UNICORN_GPU_KIT:-gpu-kit}
if [ -d "$kit" ]; then
  work=$(mktemp -d)
  wheels=()
  for whl in "$kit"/wheels/*.whl; do
    [ -e "$whl" ] || continue  # a kit without wheels
    name=$(basename "$whl")
    name=${name%%-*}
    case $name in hydra_core) module=hydra ;; antlr4_python3_runtime) module=antlr4 ;; *) module=$name ;; esac
    python3 -c "import importlib.util, sys; sys.exit(importlib.util.find_spec('$module') is not None)" && wheels+=("$whl")
  done
  if [ ${#wheels[@]} -gt 0 ]; then
    echo "installing from $kit: ${wheels[*]##*/}"
    python3 -m pip install -q --no-index --no-deps --no-compile --target "$work/site" "${wheels[@]}" || return 1
  fi
  mkdir -p "$work/cache" "$work/testdata"
  tar -xzf "$kit/cache.tar.gz" -C "$work/cache" && tar -xzf "$kit/testdata.tar.gz" -C "$work/testdata" || return 1
  export PYTHONPATH="$work/site:$PWD/src${PYTHONPATH:+:$PYTHONPATH}" UNICORN_CACHE="$work/cache"
  export UNICORN_TEST_DATA="$work/testdata"
fi
