"""The Gymnasium layer: a task's worlds as a native vector env over one Simulator, its single-world
form, and the Gymnasium ids."""
