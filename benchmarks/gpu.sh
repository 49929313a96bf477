#!/usr/bin/env bash
# The GPU numbers of benchmarks/RESULTS.md, on a machine with JAX for CUDA but without
# Pinocchio, MuJoCo or example-robot-data (the lent GPU machines: no package index there).
# The benchmarks write their JSON records to $JSON_DIR (default benchmarks/results/gpu): where
# only $OUT comes back from the machine, set JSON_DIR="$OUT/results", copy those files into
# benchmarks/results/gpu, and run `python -m benchmarks render-results`.
#
# Prepare on a machine that has them (from the repository's root):
#   python - <<'EOF'
#   import pathlib, shutil
#   from rsmooth import sim
#   sim.save_model(".gpu/solo12.npz", sim.load_urdf(sim.solo12_urdf_path()))
#   source = sim.example_robot_data_root() / "robots/solo_description"
#   target = pathlib.Path(".gpu/cmeel.prefix/share/example-robot-data/robots/solo_description")
#   for name in ("robots/solo12.urdf", "srdf/solo.srdf",  # the URDF's path, the SRDF's posture
#                "meshes/stl/solo12/solo12_upper_leg_left_side.stl"):  # a render reconstruct target
#       (target / name).parent.mkdir(parents=True, exist_ok=True)
#       shutil.copy(source / name, target / name)
#   EOF
#   pip download --no-deps --only-binary=:all: --python-version 3.12 -d .gpu/whl trimesh  # the renderer's primitives
#   # MJX for the throughput rows: a mujoco and mujoco-mjx pair of one version (the machine has JAX, etils, scipy)
#   pip download --no-deps --only-binary=:all: --python-version 3.12 --platform manylinux_2_28_x86_64 -d .gpu/whl \
#       mujoco==3.17.0 mujoco-mjx==3.17.0
# then run `bash benchmarks/gpu.sh` on the GPU machine with .gpu beside it. Each phase has
# its own time limit, so that one that hangs or fails leaves the others' numbers; the logs go
# to $OUT (default .gpu/out). The limits add up to over 20 min: where one call may run 10,
# choose with PHASES="render control ..." (on an H200: render 2 min, control 1.5, tests 1.7,
# core 0.3, sim 1.8 to 2.4 with its chunk sizes, pose 2.1, control-default 1.4, control-batched
# 1.5, pose-samples 2; on an H100 the renderer's tables alone took 150 s). A fresh machine took
# ~30 s to start.
set -u
cd "$(dirname "$0")/.."
OUT=${OUT:-.gpu/out}
JSON_DIR=${JSON_DIR:-benchmarks/results/gpu}
mkdir -p "$OUT" "$JSON_DIR"
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD:$PWD/.gpu:$PWD/.gpu/site" RSMOOTH_BENCHMARK_SOLO12_MODEL="$PWD/.gpu/solo12.npz"
PY=${PYTHON:-python3}
PHASES=${PHASES:-"info throughput render control control-batched tests core sim pose"}
# other phases, by name only: throughput-float32 pose-samples control-default reconstruct-seeds
if compgen -G ".gpu/whl/*.whl" > /dev/null; then
  $PY -m pip install -q --no-index --no-deps --no-compile --upgrade --target .gpu/site .gpu/whl/*.whl
fi

phase() {  # phase NAME LIMIT_SECONDS COMMAND...
  local name=$1 limit=$2
  shift 2
  case " $PHASES " in *" $name "*) ;; *) return 0 ;; esac
  echo "=== $name (limit ${limit} s): $*"
  local start=$SECONDS
  timeout -k 5 "$limit" "$@" > "$OUT/$name.log" 2>&1
  local rc=$?
  echo "=== $name: exit $rc after $((SECONDS - start)) s"
  tail -n "${TAIL:-40}" "$OUT/$name.log"
}

phase info 30 bash -c "nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv; \
  $PY -c 'import jax, jaxlib, equinox, optax; print(\"jax\", jax.__version__, \"equinox\", equinox.__version__, \"optax\", optax.__version__, jax.devices())'"
# Solo-12 steps per second at 1k, 4k and 16k environments, rsmooth against MJX (float64, then float32)
phase throughput 200 $PY -m benchmarks.throughput --json "$JSON_DIR"
phase throughput-float32 150 $PY -m benchmarks.throughput --float32 --json "$JSON_DIR"
phase render 300 $PY -m benchmarks render --repeats 10 --json "$JSON_DIR"
# R-DDP's samples of all nodes at once (--rddp-node-batch none: on the CPU one node at a time is
# faster); then all ten line-search step sizes at once too (DDP.line_search_batch). The first
# writes the record (control.json); the other two are comparisons, printed only.
phase control 180 $PY -m benchmarks.control --all-cpus --horizons 50 --samples 32 --iterations 4 --no-breakdown --rddp-node-batch none \
  --json "$JSON_DIR"
# the CPU-tuned defaults as they are (one node's samples at a time, one step size at a time)
phase control-default 180 $PY -m benchmarks.control --all-cpus --horizons 50 --samples 32 --iterations 4 --no-breakdown
phase control-batched 180 $PY -m benchmarks.control --all-cpus --horizons 50 --samples 32 --iterations 4 --no-breakdown \
  --rddp-node-batch none --line-search-batch 10
# The smoothing core, the perturbed optimizers, the renderer and the contact solver on the GPU,
# in float64 as the suite runs (tests that need Pinocchio, MuJoCo or trimesh are left out).
# (8 workers: each must not take 75 % of the GPU's memory, JAX's default)
phase tests 170 env XLA_PYTHON_CLIENT_PREALLOCATE=false $PY -m pytest -q -x -n 8 -p no:cacheprovider -p no:benchmark -o addopts="-ra --strict-markers" \
  tests/test_estimators.py tests/test_smooth.py tests/test_perturbed.py tests/test_noise.py tests/test_schedules.py \
  tests/render/test_raster.py tests/render/test_render.py tests/sim/test_contact.py
phase core 40 $PY -m benchmarks core --repeats 30 --json "$JSON_DIR"
# NCPSolver.chunk_size = 4 was tuned on the CPU: 16 and 64 (the whole batch) beside it
phase sim 150 $PY -m benchmarks.sim --quick --probe-timeout 30 --chunk-sizes 16 64 --json "$JSON_DIR"
# The render-pose experiment's default 100 problems at 80 deg with two restarts (two minutes here)
phase pose 220 $PY -m rsmooth.cli render pose --init-error 80 --problems 100 --seed 0 --restarts 2 \
  --method perturbed-gaussian --method soft --out "$OUT/pose80"
# 16 samples per pixel (the default is 8) from 20 and 50 deg, the default-size table's problems
phase pose-samples 240 $PY -m rsmooth.cli render pose --init-error 20 --init-error 50 --problems 100 --seed 0 \
  --samples 16 --method perturbed-gaussian --method perturbed-cauchy --out "$OUT/pose-samples"
# render reconstruct's default targets over 8 seeds, the Laplacian weight of the perturbed and
# the soft renderer (on an H100: 190 s with compilation, ~16 s per run)
phase reconstruct-seeds 240 $PY -m benchmarks.reconstruct_seeds --seeds 0 1 2 3 4 5 6 7 --json "$OUT/reconstruct-seeds.json" \
  --runs perturbed-gaussian:30 perturbed-gaussian:60 perturbed-gaussian:45 soft:30 soft:60
