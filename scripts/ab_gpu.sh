#!/usr/bin/env bash
# A/B of two versions on one GPU, alternated (machines of one kind differ by up to 15%, so compare
# only figures from one run).  OLD is a folder holding another version's abd_gym/ and envs/, e.g.
#
#     mkdir -p /tmp/old && git archive 6161796 abd_gym envs scripts/profile_env.py | tar -x -C /tmp/old
#     OUT=out bash scripts/ab_gpu.sh /tmp/old sim      # simulator: cart-pole and double pendulum
#     OUT=out bash scripts/ab_gpu.sh /tmp/old env      # vector envs (torch backend) and host profile
#
# The old version runs from its own folder: ``python -m`` puts the working directory first on
# sys.path, ahead of PYTHONPATH.  WORLDS / EWORLDS: world counts of the two parts.
set -uo pipefail
root=$PWD
old=$(cd "$1" && pwd)
part=$2
out=${OUT:-ab_out}
mkdir -p "$out"
base=$(python3 -c "import sys; print(':'.join(p for p in sys.path[1:] if p and p != '$root'))")
go() {  # version, then the command
  local v=$1; shift
  if [ "$v" = old ]; then (cd "$old" && PYTHONPATH="$old:$base" "$@"); else (cd "$root" && "$@"); fi
}
for v in old new; do go $v python3 -c "import abd_gym; print('$v ->', abd_gym.__file__)" 2>&1 | grep -- "->"; done
case $part in
sim)
  for i in 1 2; do
    for v in old new; do
      echo "== $v $i"
      go $v python3 -m abd_gym.bench --device cuda:0 --worlds "${WORLDS:-1024,16384,131072}" --cases cartpole,double_pendulum \
        --repeat 3 --out "$out/sim_${v}_$i" 2>&1 | grep "^| cartpole \|^| double_pendulum " | grep -v "0.01 |"
    done
  done ;;
env)
  for v in old new; do
    echo "== $v profile"
    if [ "$v" = old ]; then script=$old/scripts/profile_env.py; else script=$root/scripts/profile_env.py; fi
    go $v python3 "$script" --envs 1024 2>&1 | grep -v "^Module\|took\|Warning\|torch._C" | tail -n 16
  done
  for i in 1 2; do
    for v in old new; do
      echo "== $v envs $i"
      go $v python3 -m abd_gym.bench --device cuda:0 --worlds "${EWORLDS:-1024,16384}" --envs --cases cartpole \
        --tasks CartPole-v0,Pendulum-v0,DoublePendulumCart-v0 --out "$out/env_${v}_$i" 2>&1 | grep "v0 |"
    done
  done ;;
*) echo "usage: bash scripts/ab_gpu.sh OLD_TREE sim|env" >&2; exit 2 ;;
esac
