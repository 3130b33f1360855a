"""The projected liquid's pressure CG (engine/projection.py) with its two preconditioners and paths, by resolution:
MIC(0) on the serial path (the CPU's default) against the diagonal (Jacobi) on the parallel path (a GPU's default,
run here on the CPU), on the dropped half-density cube of tests/test_projection.py.

    python bench/projection_preconditioners.py [--res 12 16 24 32] [--steps 10] [--threads 2] [--body rigid]

Each (resolution, path) runs in its own child process (the choice is read when the kernels compile), `--steps`
steps of 2 ms from the drop; reported: the pressure solve's CG iterations per solve (mean and largest), the position
correction's, the seconds per pressure solve (the whole substep's solve call, host included; the CPU's, so the
parallel path's figure says nothing of a GPU's), the ratio of the two paths' seconds, and the particles' median and
largest distance between the two runs at the end (m), and the first 12 hex digits of the SHA-1 of each run's final
positions (a run with another `--threads` that gives the same digits gave the same bits). Output: bench/results/projection_preconditioners_cpu.txt.
"""
import argparse
import hashlib
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))


def child(res: int, steps: int, threads: int, body: str, serial: bool, preconditioner: str, out: str) -> dict:
    import numpy as np
    import taichi as ti

    ti.init(arch=ti.cpu, cpu_max_num_threads=threads, offline_cache=True, log_level="error")
    from fluidlab_core import materials as M
    from fluidlab_core.apps import validation

    material = (M.Rigid("rigid_500", density=500.0) if body == "rigid"
                else M.Elastic("elastic_500", density=500.0, shear_modulus=5e3, lame_lambda=1e4))
    sim, _ = validation.floating_cube_sim(res, material, M.WATER, drop=0.01, pressure="projection")
    proj = sim.solver.proj
    proj.serial_cg = serial
    proj.preconditioner = preconditioner
    seconds = []
    solve = proj.solve

    def timed(iterations, *args, **kw):
        t0 = time.perf_counter()
        solve(iterations, *args, **kw)
        if iterations is proj.iterations:  # the pressure's solve (not the position correction's)
            seconds.append(time.perf_counter() - t0)
    proj.solve = timed
    sim.step(n=1)  # compiles
    n0, seconds[:] = len(proj.iterations), []
    sim.step(n=steps - 1)
    x = sim.positions()
    np.save(out, x)
    its, pc = proj.iterations[n0:], proj.correction_iterations[n0:]
    return {"its": float(np.mean(its)), "its_max": int(max(its)), "pc": float(np.mean(pc)),
            "s": float(np.median(seconds)), "sha": hashlib.sha1(x.tobytes()).hexdigest()[:12], "unknowns": int(proj.n_unk[None]), "substeps": sim.substeps}


def main():
    import numpy as np

    from results_file import append_table

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--res", type=int, nargs="+", default=[12, 16, 24, 32])
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--body", choices=("rigid", "elastic"), default="rigid")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(**json.loads(args.child))))
        return
    rows = [f"{'cells':>5} {'unknowns':>8} {'path':<16} {'its/solve':>9} {'max':>4} {'corr its':>8} {'ms/solve':>9} "
            f"{'ratio':>6} {'sha1':>12} {'median m':>9} {'max m':>9}"]
    for res in args.res:
        got = {}
        for serial, pre in ((True, "mic"), (False, "jacobi")):
            out = f"/tmp/projection_preconditioners_{res}_{pre}.npy"
            spec = dict(res=res, steps=args.steps, threads=args.threads, body=args.body, serial=serial,
                        preconditioner=pre, out=out)
            run = subprocess.run([sys.executable, __file__, "--child", json.dumps(spec)], capture_output=True,
                                 text=True, cwd=ROOT)
            if run.returncode != 0:
                raise RuntimeError(f"{res} cells, {pre}: {run.stderr[-3000:]}")
            got[pre] = json.loads(run.stdout.strip().splitlines()[-1])
            got[pre]["x"] = np.load(out)
            print(res, pre, {k: v for k, v in got[pre].items() if k != "x"}, flush=True)
        apart = np.linalg.norm(got["mic"]["x"] - got["jacobi"]["x"], axis=1)
        for pre, path in (("mic", "serial, MIC(0)"), ("jacobi", "parallel, Jacobi")):
            g = got[pre]
            ratio = g["s"] / got["mic"]["s"]
            tail = f"{np.median(apart):9.2e} {apart.max():9.2e}" if pre == "jacobi" else ""
            rows.append(f"{res:5d} {g['unknowns']:8d} {path:<16} {g['its']:9.1f} {g['its_max']:4d} {g['pc']:8.1f} "
                        f"{1e3 * g['s']:9.2f} {ratio:6.2f} {g['sha']:>12} {tail}")
    head = [f"projection_preconditioners.py, {time.strftime('%Y-%m-%d')}, CPU, {args.threads} threads, "
            f"{args.body} 500 kg/m³ cube dropped from 10 mm onto water, {args.steps} steps of 2 ms (the first, which "
            "compiles, not counted); its/solve: the pressure CG's iterations per substep, corr its: the position "
            "correction's; ms/solve: median seconds of the pressure solve; ratio: against MIC(0)'s; median/max m: "
            "the particles' distance from the MIC(0) run at the end; sha1: of the final positions"]
    for r in rows:
        print(r)
    append_table(ROOT / "bench" / "results" / "projection_preconditioners_cpu.txt", head + rows)


if __name__ == "__main__":
    main()
