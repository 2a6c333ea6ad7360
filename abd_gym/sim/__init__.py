"""The physics as a user sees it: a Scene compiled to a Model, its per-step State, and the Simulator
that steps them."""
