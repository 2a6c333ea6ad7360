#!/usr/bin/env bash
# Every GPU measurement the README's Performance section reports, in one go, written under OUT
# (default $OUT, the device tool's output folder) and packed into one tarball, since the device
# tool returns at most 8 files.  Run from the repository root on a machine with warp (and, for the
# MuJoCo Warp rows, mujoco and mujoco_warp):
#
#     bash scripts/gpu_measure.sh [quick|full]
#
# quick (default, about 6 minutes on an H100): simulator and env tables, tolerance and scratch
# variants, the MuJoCo Warp comparison up to 131,072 worlds.  full adds the accuracy sweep of both
# mechanisms (about 10 more minutes: run it as a second call, `bash scripts/gpu_measure.sh accuracy`).
set -uo pipefail
mode=${1:-quick}
out=${OUT:-gpu_out}
dev=${DEVICE:-cuda:0}
worlds=${WORLDS:-1024,16384,131072}   # WORLDS=4,8 DEVICE=cpu: a quick smoke run of the script itself
few=${WORLDS:-1024,131072}
mkdir -p "$out"
run() {  # name, then the command; its output to $out/name.log
    local name=$1
    shift
    echo "== $name: $*"
    "$@" >"$out/$name.log" 2>&1 || echo "   (exit $?)"
    tail -n 3 "$out/$name.log"
}
if [ "$mode" = quick ] || [ "$mode" = full ]; then
    run bench python3 -m abd_gym.bench --device "$dev" --worlds "$worlds" --envs \
        --tasks CartPole-v0,Pendulum-v0,DoublePendulumCart-v0 --out "$out/bench"
    run variants python3 -m abd_gym.bench --device "$dev" --worlds "$few" --tol 1e-5,1e-3 \
        --scratch global,tiled --cases cartpole,double_pendulum,cartpole_nolimit,cartpole_bare --out "$out/variants"
    run compare python3 -m abd_gym.bench compare --device "$dev" --worlds "$worlds" --out "$out/compare"
fi
if [ "$mode" = accuracy ] || [ "$mode" = full ]; then
    run accuracy python3 -m abd_gym.bench accuracy --device "$dev" --worlds "${WORLDS:-4096}" --dtypes float32 \
        --tols 1e-5 --out "$out/accuracy"
fi
tmp=$(mktemp -d)
tar -czf "$tmp/measure_$mode.tgz" -C "$out" --exclude "*.tgz" . && mv "$tmp/measure_$mode.tgz" "$out/" \
    && echo "packed $out/measure_$mode.tgz"
