"""A material and a task written outside fluidlab_core, as a user would (docs/extending.md): the tests import
them as `tests.extension.*` and prove that the engine, the task registry, Gymnasium and sim_node take them
without any edit to the package."""
