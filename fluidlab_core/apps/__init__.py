"""Applications built on the library, reached through the `fluidlab` command: the demo scene (`demo`), the
forward throughput benchmark (`throughput`) and its Genesis comparison (`genesis_compare`), and the cellular
vortex that the viscous test and the dissipation bench share (`vortex`)."""
