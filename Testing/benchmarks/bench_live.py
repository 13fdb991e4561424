"""Benchmark: live reconstruction from a replayed 480x640 stream at 30 frames/s (issue 16).

Simulates a clavicle sweep of 480x640 frames (``--frames``, not a sweep the code was
tuned on: seed 11) and writes it to a temporary folder, then, on 127.0.0.1:

1. **accuracy**: ``bone-us-recon serve`` replays it once at ``--fps``; a live session in
   this process reconstructs it; the final surface is compared with the offline
   ``reconstruct`` of the same sweep (mean gold distance of both, and of the recorded
   frames' offline surface, which must be identical);
2. **endurance**: ``serve --loop`` for ``--seconds`` (default 180); the live session
   runs on **one core** (``sched_setaffinity``; BLAS/OpenMP threads 1), the server on
   the other. Every ``--every`` seconds it prints frames received/dropped, the frame
   rate, the refit latency after due, the frame-to-surface time and the resident
   memory (RSS and anonymous), so that a drift shows.

The server runs in its own process, so the live process pays only for receiving. The
machine may be shared: CPU seconds per frame are printed beside wall times. Run::

    python Testing/benchmarks/bench_live.py [--seconds 180] [--frames 150] [--fps 30]
        [--update-every 1] [--every 30]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import socket  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402


def mem_mb() -> tuple[float, float]:
    """(VmRSS, RssAnon) of this process in MB."""
    out = {}
    for line in open("/proc/self/status"):
        key, _, val = line.partition(":")
        if key in ("VmRSS", "RssAnon"):
            out[key] = int(val.split()[0]) / 1024
    return out.get("VmRSS", 0.0), out.get("RssAnon", 0.0)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_server(
    sweep: Path, port: int, fps: float, loop: bool, cores: set[int]
) -> subprocess.Popen:
    cmd = [
        sys.executable,
        "-m",
        "BoneUSRecon",
        "serve",
        str(sweep),
        "--port",
        str(port),
        "--fps",
        str(fps),
        "-q",
    ]
    if loop:
        cmd.append("--loop")
    p = subprocess.Popen(
        cmd, stderr=subprocess.PIPE, text=True, preexec_fn=lambda: os.sched_setaffinity(0, cores)
    )
    line = p.stderr.readline()
    if "frames/s on" not in line:
        p.kill()
        raise SystemExit(f"serve did not start: {line}{p.stderr.read()}")
    return p


def session(
    port: int,
    out: Path,
    update_every: float,
    duration: float | None,
    record: Path | None,
    on_refit=None,
):
    from BoneUSRecon.cli.igtl import FrameReceiver
    from BoneUSRecon.cli.live import run_session
    from BoneUSRecon.Logic.live import LiveParams, LiveReconstructor, PoseAssembler, SweepRecorder

    live = LiveParams(update_every_s=update_every, reconnect_s=0.5)
    receiver = FrameReceiver("127.0.0.1", port, PoseAssembler(), live).start()
    recorder = SweepRecorder(record) if record else None
    return run_session(
        receiver,
        LiveReconstructor(live=live),
        out,
        update_every_s=update_every,
        recorder=recorder,
        duration_s=duration,
        on_refit=on_refit,
    )


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--seconds", type=float, default=180.0, help="endurance replay length (default 180)"
    )
    ap.add_argument(
        "--frames", type=int, default=150, help="frames in the simulated sweep (default 150)"
    )
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--update-every", type=float, default=1.0)
    ap.add_argument("--every", type=float, default=30.0, help="print a line every S seconds")
    ap.add_argument("--seed", type=int, default=11)
    args = ap.parse_args()

    from vtkmodules.util.numpy_support import vtk_to_numpy

    from BoneUSRecon.Logic.evaluation import evaluate_surface
    from BoneUSRecon.Logic.pipeline import reconstruct
    from BoneUSRecon.Logic.sequence_io import read_sweep, write_sweep
    from BoneUSRecon.Logic.simulation import SimulationParams, simulate

    cores = sorted(os.sched_getaffinity(0))
    live_core, serve_cores = {cores[0]}, set(cores[1:] or cores)
    with tempfile.TemporaryDirectory(prefix="bench_live_") as tmp:
        d = Path(tmp)
        t = time.perf_counter()
        sim = simulate(
            SimulationParams(
                bone="clavicle",
                n_frames=args.frames,
                width=640,
                height=480,
                spacing_mm=0.075,
                seed=args.seed,
                corrupted_fraction=0.05,
            )
        )
        sweep_path = write_sweep(sim.sweep, d / "sweep.mha")
        print(
            f"simulated {args.frames} frames of 640x480 (seed {args.seed}) in {time.perf_counter() - t:.0f} s"
        )
        os.sched_setaffinity(0, live_core)

        # 1. accuracy: one pass
        port = free_port()
        server = start_server(sweep_path, port, args.fps, False, serve_cores)
        res = session(port, d / "live.vtp", args.update_every, None, d / "rec.mha")
        server.wait(timeout=30)
        offline = reconstruct(sim.sweep)
        rec_offline = reconstruct(read_sweep(res.record))
        same = np.array_equal(
            vtk_to_numpy(res.final.surface.GetPoints().GetData()),
            vtk_to_numpy(rec_offline.surface.GetPoints().GetData()),
        )
        m_live = evaluate_surface(res.final.surface, sim.gold).mean
        m_off = evaluate_surface(offline.surface, sim.gold).mean
        lat = np.array(res.latencies_s) * 1000
        print(f"\n1. accuracy (one pass at {args.fps:g} frames/s)")
        print(f"  frames received / dropped : {res.received} / {res.counts['dropped']}")
        print(
            f"  mean gold distance        : live {m_live:.4f} mm, offline {m_off:.4f} mm, "
            f"difference {abs(m_live - m_off):.4f} mm"
        )
        print(f"  live = offline(recorded)  : {'identical' if same else 'DIFFERENT'}")
        print(
            f"  refit latency after due   : median {np.median(lat):.0f} ms, max {lat.max():.0f} ms"
        )
        cpu_refit = np.array(res.refit_cpu_s) * 1000
        print(
            f"  refit + write CPU time    : median {np.median(cpu_refit):.0f} ms, max {cpu_refit.max():.0f} ms"
        )

        # 2. endurance: looped replay on one core
        port = free_port()
        server = start_server(sweep_path, port, args.fps, True, serve_cores)
        t0 = time.monotonic()
        c0 = time.process_time()
        rows: list[str] = []
        state = {"next": t0 + args.every, "last_n": 0, "last_t": t0}

        def on_refit(r) -> None:
            now = time.monotonic()
            if now < state["next"]:
                return
            rss, anon = mem_mb()
            lat = np.array(r.latencies_s[-int(args.every / args.update_every) :]) * 1000
            f2s = np.array(r.frame_to_surface_s[-len(lat) :]) * 1000
            rate = (r.received - state["last_n"]) / (now - state["last_t"])
            rows.append(
                f"  {now - t0:6.0f} s {r.received:7d} {sum(r.skipped.values()):5d}"
                f" {receiver_dropped(r):6d} {rate:7.1f} {np.median(lat):7.0f} {lat.max():6.0f}"
                f" {f2s[:, 0].mean():7.0f} {f2s[:, 1].max():6.0f} {rss:7.0f} {anon:7.0f}"
            )
            print(rows[-1], flush=True)
            state.update(next=state["next"] + args.every, last_n=r.received, last_t=now)

        print(
            f"\n2. endurance: looped replay for {args.seconds:.0f} s at {args.fps:g} frames/s, live on core {cores[0]}"
        )
        print(
            "       time  frames  skip  drops  fr/s  lat med  max  f2s mean  max  RSS MB  anon MB"
        )
        try:
            res = session(port, d / "live2.vtp", args.update_every, args.seconds, None, on_refit)
        finally:
            server.kill()
            server.wait()
        cpu = time.process_time() - c0
        lat = np.array(res.latencies_s) * 1000
        print(
            f"  frames {res.received}, dropped {res.counts['dropped']}, kept for the surface "
            f"{res.final.summary['frames']} (thinned beyond max_frames)"
        )
        print(
            f"  sustained rate {res.received / res.elapsed_s:.1f} frames/s; CPU {1000 * cpu / max(res.received, 1):.1f} ms per frame "
            f"({100 * cpu / res.elapsed_s:.0f} % of one core)"
        )
        print(
            f"  refit latency after due: median {np.median(lat):.0f} ms, p95 {np.percentile(lat, 95):.0f} ms, "
            f"max {lat.max():.0f} ms over {lat.size} refits"
        )
        cpu_refit = np.array(res.refit_cpu_s) * 1000
        print(
            f"  refit + write CPU time (the latency on an idle core): median "
            f"{np.median(cpu_refit):.0f} ms, p95 {np.percentile(cpu_refit, 95):.0f} ms, max {cpu_refit.max():.0f} ms"
        )


def receiver_dropped(r) -> int:
    return int(r.counts.get("dropped", 0)) if r.counts else -1


if __name__ == "__main__":
    main()
