#!/usr/bin/env bash
# Every GPU measurement the README's Performance section reports, written under OUT (default $OUT,
# the device tool's output folder) and packed into one tarball, since the device tool returns at
# most 8 files.  Run from the repository root on a machine with warp (and, for the MuJoCo Warp
# rows, mujoco and mujoco_warp):
#
#     bash scripts/gpu_measure.sh [PART ...]
#
# PARTs: bench (simulator and env tables), reuse (Newton's factor reuse on and off), variants
# (tolerance, the global / shared / lane-split steps, the cart-pole without limit / drive), split (the step's device time
# in one launch and with its open and close kernels launched around Newton), envelope (a 10-link chain with
# the dense and the envelope factor), compare (MuJoCo Warp, up to
# 131,072 worlds and 1M of ours), accuracy (speed against error, both mechanisms), tests (the test
# files that build their simulators on the default device, run there with ABD_GYM_DEVICE=$DEVICE,
# and the vector env's CUDA cases; needs pytest on the machine); default: bench reuse variants compare.  Each part takes a few
# minutes on an H100; keep a device call under its 10-minute limit by splitting the parts.
set -uo pipefail
parts=${*:-bench reuse variants compare}
out=${OUT:-gpu_out}
dev=${DEVICE:-cuda:0}
worlds=${WORLDS:-1024,16384,131072}   # WORLDS=4,8 DEVICE=cpu: a quick smoke run of the script itself
# CASES=cartpole: the accuracy part for one mechanism (one device call each keeps it under 10 minutes)
few=${WORLDS:-1024,131072}
mkdir -p "$out"
run() {  # name, then the command; its output to $out/name.log
    local name=$1
    shift
    echo "== $name: $*"
    "$@" >"$out/$name.log" 2>&1 || echo "   (exit $?)"
    tail -n 3 "$out/$name.log"
}
for part in $parts; do
    case $part in
    bench) run bench python3 -m abd_gym.bench --device "$dev" --worlds "$worlds" --envs --repeat 3 \
        --tasks CartPole-v0,Pendulum-v0,DoublePendulumCart-v0 --out "$out/bench" ;;
    reuse) run reuse python3 -m abd_gym.bench --device "$dev" --worlds "$worlds" --reuse-factor auto,0 \
        --cases cartpole,double_pendulum --out "$out/reuse" ;;
    variants) run variants python3 -m abd_gym.bench --device "$dev" --worlds "$few" --tol 1e-5,1e-3 \
        --scratch global,shared,lanes --cases cartpole,double_pendulum,cartpole_nolimit,cartpole_bare --out "$out/variants" ;;
    envelope) run envelope python3 -m abd_gym.bench --device "$dev" --worlds "$few" --cases chain10 --envelope 0,1 \
        --out "$out/envelope" ;;
    split) for c in cartpole double_pendulum; do for w in $(echo "${WORLDS:-1024,16384}" | tr , ' '); do
            for launch in one two; do
                run "split_${c}_${w}_$launch" python3 scripts/profile_step.py --device "$dev" --case "$c" --worlds "$w" \
                    --split --steps 400 --launch $launch
            done
        done; done ;;
    compare) run compare python3 -m abd_gym.bench compare --device "$dev" --worlds "$worlds" --out "$out/compare" ;;
    accuracy) run accuracy python3 -m abd_gym.bench accuracy --device "$dev" --worlds "${WORLDS:-4096}" \
        --dtypes float32 --tols 1e-5 --reuse-factors auto,0 --cases "${CASES:-double_pendulum,cartpole}" \
        --out "$out/accuracy" ;;
    tests) ABD_GYM_DEVICE=$dev run tests python3 -m pytest -q -p no:cacheprovider tests/test_graph.py tests/test_physics.py \
        tests/test_hard_cases.py tests/test_integrators.py tests/test_drives.py tests/test_envelope.py \
        "tests/test_constitutions.py::test_fused_assembly_matches_staged" "tests/test_constitutions.py::test_prismatic_joint_to_a_fixed_body" \
        "tests/test_vector_env.py::test_torch_backend_matches_numpy_and_stays_on_device" \
        "tests/test_vector_env.py::test_graph_step_matches_launched_step" \
        "tests/test_vector_env.py::test_nan_actions_checked_on_the_device_are_taken_back" -k "not cpu" ;;
    *) echo "unknown part $part (bench, reuse, variants, split, envelope, compare, accuracy, tests)" >&2; exit 2 ;;
    esac
done
tmp=$(mktemp -d)
tar -czf "$tmp/measure.tgz" -C "$out" --exclude "*.tgz" . && mv "$tmp/measure.tgz" "$out/" \
    && echo "packed $out/measure.tgz"
