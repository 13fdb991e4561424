"""``bone-us-recon live --host H --port P -o SURFACE``: the surface grows while the user scans.

Connects to an OpenIGTLink server (a PlusServer, or ``bone-us-recon serve``),
segments every frame as it arrives, refits the surface every ``--update-every``
seconds from all frames so far, writes it (atomically) and optionally sends it back
as a POLYDATA message. Ctrl-C, ``--duration`` or the server going away ends the
session: the final surface (the same as an offline ``reconstruct`` of the received
frames) is written, and with ``--record`` the received frames as a PLUS sequence.

``--bone-point X Y Z`` (as for ``reconstruct``) makes the track follow the bone through
the point once the probe reaches it. A point cannot be checked against a sweep that has
not arrived, so a point off the scan is reported at the end, as a warning on stderr and
in the JSON summary's ``warnings`` (``reconstruct`` refuses it, exit 2): the scan is
over and its surface, made as without the point, is kept.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from BoneUSRecon.cli.common import (
    SURFACE_HELP,
    add_common_options,
    add_json_option,
    print_json,
    print_summary,
    print_warnings,
)
from BoneUSRecon.cli.reconstruct import add_reconstruction_options, params_from_args

__all__ = ["register", "run", "run_demo", "run_session", "SessionResult"]

DEFAULT_PORT = 18944  # the OpenIGTLink port PlusServer and Slicer use
#: GIL switch interval during a session (s): see :func:`run_session`.
RECEIVE_SWITCH_S = 0.001


def register(subparsers: Any) -> None:
    """Add the ``live`` sub-command."""
    p = subparsers.add_parser(
        "live",
        help="reconstruct live from an OpenIGTLink stream (PLUS server)",
        description="Receive tracked frames over OpenIGTLink (IMAGE, TRANSFORM), segment "
        "each as it arrives, refit and write the surface every few seconds, and at the "
        "end (Ctrl-C, --duration, or the server closing) write the final surface and, "
        "with --record, the received frames as a PLUS sequence.",
    )
    p.add_argument("--host", default="127.0.0.1", help="server address (default 127.0.0.1)")
    p.add_argument(
        "--port", type=int, default=DEFAULT_PORT, help=f"server port (default {DEFAULT_PORT})"
    )
    p.add_argument(
        "-o",
        "--output",
        required=True,
        metavar="SURFACE",
        help=SURFACE_HELP + ", rewritten at each refit",
    )
    p.add_argument(
        "--image", metavar="NAME", help="IMAGE device name to use (default: the first one received)"
    )
    p.add_argument(
        "--transform",
        metavar="NAME",
        help="pose from TRANSFORM messages: ImageToReference (or any ImageTo<X>, composed "
        "from the transforms received), or ProbeToTracker-style (default: the IMAGE's own matrix)",
    )
    p.add_argument(
        "--calibration",
        metavar="XML",
        help="PLUS device-set XML with the ImageToProbe calibration: pose = "
        "inv(ReferenceToTracker) * ProbeToTracker * ImageToProbe",
    )
    p.add_argument(
        "--update-every",
        type=float,
        default=1.0,
        metavar="S",
        help="seconds between refits (default 1)",
    )
    p.add_argument(
        "--send-surface",
        metavar="NAME",
        help="send each surface back as a POLYDATA message of this name",
    )
    p.add_argument(
        "--record", metavar="SWEEP", help="save the received frames as a PLUS sequence (.mha/.mhd)"
    )
    p.add_argument(
        "--duration",
        type=float,
        metavar="S",
        help="stop after S seconds (default: until the server stops or Ctrl-C)",
    )
    p.add_argument(
        "--reconnect",
        type=float,
        default=3.0,
        metavar="S",
        help="after a disconnection, try reconnecting for S seconds (default 3)",
    )
    p.add_argument(
        "--queue",
        type=int,
        default=64,
        metavar="N",
        help="frames waiting to be processed before new ones are dropped (default 64)",
    )
    add_reconstruction_options(p)
    add_json_option(p)
    add_common_options(p)
    p.set_defaults(func=run)


@dataclass
class SessionResult:
    """What a live session did (the CLI's summary; the benchmark's figures)."""

    received: int = 0
    skipped: Counter[str] = field(default_factory=Counter)
    refits: int = 0
    #: Per refit, seconds from when it was due to the surface written (and sent):
    #: ``refit_wait_s + refit_s``.
    latencies_s: list[float] = field(default_factory=list)
    #: Per refit, seconds from due to its start: the frame in hand is finished first.
    refit_wait_s: list[float] = field(default_factory=list)
    #: Per refit, wall seconds of the refit, the write and the send.
    refit_s: list[float] = field(default_factory=list)
    #: CPU seconds of this thread per refit (refit + write + send): the latency on an idle core.
    refit_cpu_s: list[float] = field(default_factory=list)
    #: Per refit, (mean, max) seconds from a frame's arrival to the surface holding it.
    frame_to_surface_s: list[tuple[float, float]] = field(default_factory=list)
    waiting: str = ""
    recon: Any = None
    final: Any = None
    record: Path | None = None
    elapsed_s: float = 0.0
    interrupted: bool = False
    counts: dict[str, int] = field(default_factory=dict)

    @property
    def warnings(self) -> tuple[str, ...]:
        """The final surface's warnings, one sentence each (e.g. a bone point off the
        scan or that no contour reaches); empty without a final surface."""
        return tuple(self.final.summary["warnings"]) if self.final is not None else ()


class _Status:
    """One status line on stderr, redrawn in place on a terminal."""

    def __init__(self, quiet: bool) -> None:
        self.on = not quiet and sys.stderr.isatty()
        self.width = 0

    def show(self, text: str) -> None:
        if self.on:
            pad = max(0, self.width - len(text))
            sys.stderr.write("\r" + text + " " * pad)
            sys.stderr.flush()
            self.width = len(text)

    def close(self) -> None:
        if self.on and self.width:
            sys.stderr.write("\n")
            sys.stderr.flush()


def _status_text(res: SessionResult, rate: float, receiver: Any) -> str:
    from BoneUSRecon.Logic.live import stats_row

    st = stats_row(res.recon)
    skipped = sum(res.skipped.values())
    text = (
        f"frames {res.received} received, {st['used']} used, {st['rejected']} rejected, "
        f"{skipped} skipped, {receiver.counts['dropped']} dropped | {rate:4.1f} frames/s | "
        f"coverage {100 * st['coverage']:.0f}%"
    )
    if res.waiting:
        text += f" | waiting: {res.waiting}"
    elif res.latencies_s:
        text += f" | surface {1000 * res.latencies_s[-1]:.0f} ms after due"
    return text


def run_session(
    receiver: Any,
    recon: Any,
    out: Path,
    *,
    update_every_s: float,
    recorder: Any = None,
    send_surface: str | None = None,
    duration_s: float | None = None,
    quiet: bool = True,
    on_refit: Any = None,
) -> SessionResult:
    """Receive, reconstruct and write until the stream ends; then the final surface.

    Parameters
    ----------
    receiver : FrameReceiver
        Started.
    recon : LiveReconstructor
    out : Path
        Surface file, rewritten (atomically) at each refit.
    update_every_s : float
    recorder : SweepRecorder, optional
    send_surface : str, optional
        POLYDATA device name for sending each surface back.
    duration_s : float, optional
    quiet : bool
        No status line.
    on_refit : callable, optional
        Called with the :class:`SessionResult` after each refit (benchmarks).

    Returns
    -------
    SessionResult
        ``final`` is None when no surface could be built (``waiting`` says why).
    """
    from BoneUSRecon.cli.igtl import polydata_message
    from BoneUSRecon.Logic.errors import BoneUSReconError
    from BoneUSRecon.Logic.vtkio import write_polydata

    res = SessionResult(counts=receiver.counts)  # the receiver's live counts until the end
    # The receiving thread needs the GIL for a moment per message. Python hands it
    # over every 5 ms by default, and a thread asking for it behind a busy one may wait
    # several of those periods (up to ~90 ms measured during a refit); at 1 ms the
    # receiving thread never waited more than ~17 ms, half a frame at 30 frames/s.
    switch = sys.getswitchinterval()
    sys.setswitchinterval(min(switch, RECEIVE_SWITCH_S))
    status = _Status(quiet)
    t0 = time.monotonic()
    due = t0 + update_every_s
    new = 0
    window: list[float] = []
    pending: list[float] = []  # arrival times of frames not yet in a surface

    def take(f: Any) -> None:
        nonlocal new
        res.received += 1
        window.append(time.monotonic())
        pending.append(window[-1])
        if recorder is not None and f.image is not None:
            recorder.add(f.image, f.pose, f.timestamp)
        if f.problem:
            res.skipped[f.problem] += 1
            return
        wrong_size = recon.counts["wrong_size"]
        if recon.add_frame(f.image, f.pose, f.timestamp) is not None:
            new += 1
        elif recon.counts["wrong_size"] > wrong_size:
            res.skipped["image size differs from the first frame's"] += 1

    def publish(r: Any, fast: bool = False) -> None:
        # Refits rewrite the file every few seconds: the fast .vtp flavour (LZ4, ~3 ms
        # instead of ~55 ms of CPU for 10,000 points); the final surface the usual one.
        write_polydata(r.surface, out, fast=fast)
        if send_surface:
            receiver.send(polydata_message(r.surface, send_surface))

    try:
        while True:
            now = time.monotonic()
            if duration_s is not None and now - t0 >= duration_s:
                break
            if recon.owed and receiver.queue.empty():
                recon.work(0.005)  # spare time: a slice of the links a thinning left owed
            f = receiver.get(timeout=max(0.0, min(0.05, due - now)))
            if f is not None:
                take(f)
            elif receiver.ended and receiver.queue.empty():
                break
            now = time.monotonic()
            if now < due:
                continue
            if new and receiver.queue.qsize() > receiver.queue.maxsize // 2:
                # Falling behind (a busy core): frames first. A late refit is only late,
                # a dropped frame is lost to the surface for good.
                continue
            spent = 0.0
            if new:
                try:
                    t, c = time.monotonic(), time.thread_time()
                    res.recon = recon.refit(with_points=False)
                    publish(res.recon, fast=True)
                    done = time.monotonic()
                    res.refit_cpu_s.append(time.thread_time() - c)
                    res.refit_wait_s.append(t - due)
                    res.refit_s.append(done - t)
                    res.latencies_s.append(done - due)
                    spent = done - t
                    if pending:
                        res.frame_to_surface_s.append(
                            (done - sum(pending) / len(pending), done - pending[0])
                        )
                    pending.clear()
                    res.refits += 1
                    res.waiting = ""
                    if on_refit is not None:
                        on_refit(res)
                except BoneUSReconError as exc:
                    res.waiting = exc.message
                new = 0
            window = [w for w in window if w > now - 2.0]
            rate = len(window) / min(2.0, max(now - t0, 1e-3))
            status.show(_status_text(res, rate, receiver))
            # The next refit no sooner than this one took: frames get at least half of
            # the time even when refits are slower than --update-every (else one frame
            # between two refits, and the queue overflows).
            due = max(due + update_every_s, time.monotonic() + spent)
    except KeyboardInterrupt:
        res.interrupted = True
    finally:
        receiver.stop()
        sys.setswitchinterval(switch)
    # What was already received is part of the session (bounded by the queue).
    while (f := receiver.get(timeout=0.0)) is not None:
        take(f)
    status.close()
    res.counts = dict(receiver.counts)
    res.elapsed_s = time.monotonic() - t0
    try:
        res.final = recon.refit(final=True)
        publish(res.final)
        res.recon = res.final
    except BoneUSReconError as exc:
        res.waiting = exc.message
    if recorder is not None:
        res.record = recorder.finish()
    return res


def _check_outputs(args: argparse.Namespace) -> tuple[Path, Path | None]:
    from BoneUSRecon.Logic.errors import BoneUSReconError
    from BoneUSRecon.Logic.fileio import check_input_file, check_output_path
    from BoneUSRecon.Logic.vtkio import SURFACE_EXTENSIONS

    out = check_output_path(args.output, SURFACE_EXTENSIONS)
    record = check_output_path(args.record, (".mha", ".mhd")) if args.record else None
    if args.calibration:
        cal = check_input_file(args.calibration)
        for p in (out, record):
            if p is not None and p.resolve() == cal.resolve():
                raise BoneUSReconError("output path is also the calibration input", p)
    if record is not None and record.resolve() == out.resolve():
        raise BoneUSReconError("--record and -o name the same file", record)
    if not 0 < args.update_every <= 3600:
        raise BoneUSReconError(f"--update-every must be in (0, 3600] s, got {args.update_every}")
    if args.duration is not None and not args.duration > 0:
        raise BoneUSReconError(f"--duration must be > 0 s, got {args.duration}")
    if not 0 < args.port < 65536:
        raise BoneUSReconError(f"--port must be in 1..65535, got {args.port}")
    return out, record


def run(args: argparse.Namespace) -> int:
    """Run a live session; print its summary."""
    from BoneUSRecon.cli.igtl import FrameReceiver
    from BoneUSRecon.Logic.errors import BoneUSReconError
    from BoneUSRecon.Logic.live import LiveParams, LiveReconstructor, PoseAssembler, SweepRecorder

    out, record = _check_outputs(args)
    params = params_from_args(args)
    live = LiveParams(
        update_every_s=args.update_every, queue_frames=args.queue, reconnect_s=args.reconnect
    )
    assembler = PoseAssembler(
        transform=args.transform,
        calibration=args.calibration,
        image_name=args.image,
        tolerance_s=live.pose_tolerance_s,
    )
    receiver = FrameReceiver(args.host, args.port, assembler, live).start()
    if not args.quiet and not args.json:
        print(
            f"live: connected to {receiver.where}; pose from {assembler.mode}; "
            "Ctrl-C ends the session",
            file=sys.stderr,
        )
    recorder = SweepRecorder(record) if record is not None else None
    try:
        res = run_session(
            receiver,
            LiveReconstructor(params, live),
            out,
            update_every_s=args.update_every,
            recorder=recorder,
            send_surface=args.send_surface,
            duration_s=args.duration,
            quiet=args.quiet or args.json,
        )
    except BaseException:
        receiver.stop()
        if recorder is not None:
            recorder.discard()
        raise
    if res.final is None:
        raise BoneUSReconError(
            f"no surface after {res.received} frames: {res.waiting}"
            + (f" (frames saved to {res.record})" if res.record else ""),
            receiver.where,
        )
    return _report(args, res, out, receiver.where)


def summary_doc(res: SessionResult, out: Path, where: str) -> dict[str, Any]:
    """The session as one JSON-ready dict."""
    import numpy as np

    from BoneUSRecon.Logic.live import stats_row

    lat = np.array(res.latencies_s) if res.latencies_s else np.zeros(1)
    return {
        "server": where,
        "output": str(out),
        "record": str(res.record) if res.record else None,
        "received_frames": res.received,
        "skipped_frames": sum(res.skipped.values()),
        "skipped": dict(res.skipped),
        "dropped_frames": res.counts.get("dropped", 0),
        "reconnects": res.counts.get("reconnects", 0),
        **{
            f"{k}_frames" if k != "coverage" else "grid_coverage": v
            for k, v in stats_row(res.final).items()
        },
        "refits": res.refits,
        "latency_s": {"median": float(np.median(lat)), "max": float(lat.max())},
        "elapsed_s": res.elapsed_s,
        "frames_per_s": res.received / max(res.elapsed_s, 1e-9),
        "interrupted": res.interrupted,
        "summary": res.final.summary,
    }


def _report(args: argparse.Namespace, res: SessionResult, out: Path, where: str) -> int:
    doc = summary_doc(res, out, where)
    s = res.final.summary
    if args.json:
        print_json(doc)
        print_warnings(s["warnings"])
        return 0
    rows: list[tuple[str, Any]] = [
        (
            "frames received",
            f"{res.received} in {res.elapsed_s:.1f} s ({doc['frames_per_s']:.1f} frames/s)",
        ),
        (
            "frames used",
            f"{doc['used_frames']} ({doc['rejected_frames']} rejected by segmentation or fit)",
        ),
        (
            "frames skipped",
            f"{doc['skipped_frames']} without a usable pose, {doc['dropped_frames']} dropped (queue full)",
        ),
        (
            "grid",
            f"{s['grid_shape'][0]} slices x {s['grid_shape'][1]} rays, {100 * s['grid_coverage']:.1f}% covered",
        ),
        (
            "refits",
            f"{res.refits}, surface {1000 * doc['latency_s']['median']:.0f} ms "
            f"(max {1000 * doc['latency_s']['max']:.0f} ms) after due",
        ),
        ("surface", f"{s['surface_triangles']} triangles, {s['surface_area_mm2']:.0f} mm^2"),
        ("written", str(out)),
    ]
    if res.record:
        rows.append(("recorded", str(res.record)))
    for problem, n in res.skipped.most_common(3):
        rows.append(("skipped because", f"{problem} ({n})"))
    end = "interrupted" if res.interrupted else "ended"
    print_summary(f"Live session with {where} {end}", rows)
    # Bone points no contour reaches, or off the whole scan: warned, not refused (the
    # scan cannot be given again; :func:`BoneUSRecon.Logic.live._point_warnings`).
    print_warnings(s["warnings"])
    return 0


def run_demo(args: argparse.Namespace, sim_params: Any) -> int:
    """``demo --live``: simulate, replay over 127.0.0.1 as ``serve``, reconstruct as ``live``.

    Writes the simulation, the live surface (``live_surface.vtp``) and the offline one
    (``surface.vtp``) into OUTDIR, and prints how the live surface compares.
    """
    import threading

    from BoneUSRecon.cli.common import removed_on_failure
    from BoneUSRecon.cli.igtl import FrameReceiver, SweepServer
    from BoneUSRecon.Logic.errors import BoneUSReconError
    from BoneUSRecon.Logic.evaluation import evaluate_surface
    from BoneUSRecon.Logic.fileio import check_output_dir
    from BoneUSRecon.Logic.live import LiveParams, LiveReconstructor, PoseAssembler
    from BoneUSRecon.Logic.pipeline import reconstruct
    from BoneUSRecon.Logic.simulation import simulate, write_simulation
    from BoneUSRecon.Logic.vtkio import read_points, write_polydata

    outdir = check_output_dir(args.outdir)
    quiet = args.quiet or args.json
    with removed_on_failure(outdir):
        sim = simulate(sim_params)
        files = write_simulation(sim, outdir)
        gold = read_points(files["gold"])
        server = SweepServer(sim.sweep, "127.0.0.1", 0, fps=30.0)
        thread = threading.Thread(target=server.serve, name="demo-serve", daemon=True)
        thread.start()
        live = LiveParams(reconnect_s=0.5)
        try:
            receiver = FrameReceiver("127.0.0.1", server.port, PoseAssembler(), live).start()
            if not quiet:
                print(
                    f"demo --live: serving {sim.sweep.n_frames} frames at 30 frames/s on "
                    f"127.0.0.1:{server.port}; reconstructing live",
                    file=sys.stderr,
                )
            res = run_session(
                receiver,
                LiveReconstructor(live=live),
                outdir / "live_surface.vtp",
                update_every_s=live.update_every_s,
                quiet=quiet,
            )
        finally:
            server.stop()
            thread.join(timeout=5)
        if res.final is None:
            raise BoneUSReconError(f"no live surface: {res.waiting}", outdir)
        offline = reconstruct(sim.sweep)
        write_polydata(offline.surface, outdir / "surface.vtp")
    m_live = evaluate_surface(res.final.surface, gold).mean
    m_off = evaluate_surface(offline.surface, gold).mean
    doc = summary_doc(res, outdir / "live_surface.vtp", f"127.0.0.1:{server.port}")
    doc.update(gold_mean_mm={"live": m_live, "offline": m_off})
    if args.json:
        print_json(doc)
        return 0
    print_summary(
        f"Demo --live: {sim_params.bone} phantom served and reconstructed live",
        [
            ("frames received", f"{res.received} ({doc['dropped_frames']} dropped)"),
            (
                "refits",
                f"{res.refits}, surface {1000 * doc['latency_s']['median']:.0f} ms after due",
            ),
            ("gold distance mean", f"live {m_live:.3f} mm, offline {m_off:.3f} mm"),
            ("live surface", str(outdir / "live_surface.vtp")),
            ("offline surface", str(outdir / "surface.vtp")),
            ("sweep (PLUS .mha)", str(files["sweep"])),
        ],
    )
    return 0
