"""Forward throughput of the MPM engine (particle-substeps per second) at 20k, 50k and 100k particles on a
64³ grid, with peak memory, and the Genesis ratio when genesis-world is installed.

    python bench/bench_mpm.py [--arch cpu|cuda] [--steps N]

Prints a table and writes it to bench/results/mpm_forward_<backend>.txt.
"""
import argparse
import platform
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import fluidlab_core  # noqa: E402
from fluidlab_core.apps import throughput as bench  # noqa: E402


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--arch", default="cpu", choices=["cpu", "cuda", "auto"])
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--particles", type=int, nargs="+", default=[20_000, 50_000, 100_000])
    args = parser.parse_args()
    cfg = fluidlab_core.init(arch=args.arch)
    lines = [f"# {platform.processor() or platform.machine()}, {platform.python_version()}"]

    def log(line):
        print(line, flush=True)
        lines.append(line)

    bench.main(particles=args.particles, steps=args.steps, log=log)
    out = Path(__file__).resolve().parent / "results" / f"mpm_forward_{cfg.backend}.txt"
    out.parent.mkdir(exist_ok=True)
    out.write_text("\n".join(lines) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
