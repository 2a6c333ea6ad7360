"""The benchmarks (``python -m abd_gym.bench``): speed against worlds, against MuJoCo, against error,
and the hard cases."""
