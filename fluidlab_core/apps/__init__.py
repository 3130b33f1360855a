"""Applications built on the library, reached through the `fluidlab` command: the demo scene (`demo`), the
forward throughput benchmark (`throughput`) and its Genesis comparison (`genesis_compare`), the cellular
vortex that the viscous test and the dissipation bench share (`vortex`), and the physics validation scenes
(dam break, hydrostatics, Rayleigh–Taylor, floating cube, sound ring) that the tests run at one size and
bench/convergence.py at three (`validation`)."""
