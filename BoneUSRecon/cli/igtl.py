"""OpenIGTLink edge of live reconstruction: a receiving client and a replaying server.

Network I/O for the ``live`` and ``serve`` commands (and the benchmark), kept out of
:mod:`BoneUSRecon.Logic` (pure computation, and what the Slicer module installs: Slicer
receives OpenIGTLink with its own OpenIGTLinkIF, so it never needs :mod:`pyigtl`).

The wire format (message headers, IMAGE, TRANSFORM, POLYDATA bodies, metadata) is
:mod:`pyigtl`'s. Its client and server classes are not used: ``OpenIGTLinkClient``
keeps only the latest message per device (a frame arriving before the previous one
is read is lost without a trace) and does not notice a server closing the
connection, and ``OpenIGTLinkServer`` takes over SIGINT/SIGTERM. The small socket
loops below keep every message, count what they drop (a bounded queue: memory never
grows when frames come faster than they are processed), reconnect after a
disconnection, and give one-line errors for a port in use or nothing listening.

:class:`FrameReceiver` runs in a thread and hands :class:`~BoneUSRecon.Logic.live.PosedFrame`
objects to the caller's loop; :class:`SweepServer` replays a recorded sweep as a PLUS
server would (IMAGE with its ``ImageToReference`` matrix; or IMAGE in pixels plus a
TRANSFORM ``ImageToReference``; or, with a calibration, IMAGE plus ``ProbeToTracker``
and ``ReferenceToTracker`` TRANSFORMs, as PlusServer sends them).
"""

from __future__ import annotations

import contextlib
import queue
import socket
import struct
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import pyigtl
from vtkmodules.util.numpy_support import vtk_to_numpy
from vtkmodules.vtkCommonDataModel import vtkPolyData

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.live import LiveParams, PoseAssembler, PosedFrame
from BoneUSRecon.Logic.sweep import Sweep

__all__ = ["FrameReceiver", "SweepServer", "SERVE_MODES", "open_listener", "polydata_message"]

HEADER_SIZE = pyigtl.MessageBase.IGTL_HEADER_SIZE
#: Largest message body accepted (bytes): a 4K RGBA frame is ~33 MB; anything beyond
#: is a corrupt header, not an image.
MAX_BODY = 256 << 20
#: How the replaying server sends a frame's pose.
SERVE_MODES = ("image", "transform", "plus")


def _where(host: str, port: int) -> str:
    return f"{host}:{port}"


# ------------------------------------------------------------------------------------
# Client
# ------------------------------------------------------------------------------------
class _Closed(Exception):
    """The peer closed the connection."""


def _recv_exact(sock: socket.socket, n: int, stop: threading.Event) -> bytes:
    """``n`` bytes from ``sock`` (a socket with a short timeout); raises :class:`_Closed`."""
    buf = bytearray(n)
    view = memoryview(buf)
    got = 0
    while got < n:
        if stop.is_set():
            raise _Closed
        try:
            k = sock.recv_into(view[got:], n - got)
        except TimeoutError:
            continue
        except OSError:
            raise _Closed from None
        if k == 0:
            raise _Closed
        got += k
    return bytes(buf)


def connect(host: str, port: int, timeout: float = 2.0) -> socket.socket:
    """A TCP connection to an OpenIGTLink server, or a one-line error.

    Raises
    ------
    BoneUSReconError
        Nothing listening, host unknown or unreachable (the message names ``host:port``).
    """
    try:
        sock = socket.create_connection((host, port), timeout=timeout)
    except ConnectionRefusedError:
        raise BoneUSReconError(
            "cannot connect: nothing is listening there (is the PLUS server running?)",
            _where(host, port),
        ) from None
    except socket.gaierror as exc:
        raise BoneUSReconError(
            f"cannot connect: unknown host ({exc.strerror})", _where(host, port)
        ) from None
    except OSError as exc:
        raise BoneUSReconError(
            f"cannot connect: {exc.strerror or exc or 'timed out'}", _where(host, port)
        ) from None
    sock.settimeout(0.05)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return sock


def _status(msg: Any) -> str:
    """A TRANSFORM's tracking status from its metadata (PLUS, OpenIGTLink 3); OK if none."""
    meta = getattr(msg, "metadata", None) or {}
    for key in ("TransformStatus", "Status"):
        if key in meta:
            return str(meta[key]).strip() or "OK"
    return "OK"


class FrameReceiver:
    """Receive IMAGE and TRANSFORM messages in a thread; posed frames in a bounded queue.

    Parameters
    ----------
    host, port : str, int
    assembler : PoseAssembler
        Pairs images with their transforms (used only in the receiving thread).
    live : LiveParams
        ``queue_frames`` and ``reconnect_s``.

    Attributes
    ----------
    counts : dict
        ``images`` (IMAGE messages of the chosen device), ``transforms``, ``dropped``
        (queue full), ``malformed``, ``other`` (other message types), ``reconnects``.
    """

    def __init__(
        self,
        host: str,
        port: int,
        assembler: PoseAssembler,
        live: LiveParams = LiveParams(),  # noqa: B008 (frozen)
    ) -> None:
        self.host, self.port = host, int(port)
        self.assembler = assembler
        self.live = live
        self.queue: queue.Queue[PosedFrame] = queue.Queue(maxsize=int(live.queue_frames))
        self.counts = {
            "images": 0,
            "transforms": 0,
            "dropped": 0,
            "malformed": 0,
            "other": 0,
            "reconnects": 0,
        }
        self._stop = threading.Event()
        self._ended = threading.Event()
        self._send_lock = threading.Lock()
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None

    @property
    def where(self) -> str:
        """``host:port``."""
        return _where(self.host, self.port)

    @property
    def ended(self) -> bool:
        """True once the server has gone (and did not come back) or :meth:`stop` was called."""
        return self._ended.is_set()

    def start(self) -> FrameReceiver:
        """Connect (a one-line error if nothing listens) and start receiving."""
        self._sock = connect(self.host, self.port)
        self._thread = threading.Thread(target=self._run, name="igtl-receiver", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop receiving and close the connection."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._close()
        self._ended.set()

    def get(self, timeout: float) -> PosedFrame | None:
        """The next posed frame, or None after ``timeout`` seconds."""
        try:
            return self.queue.get(timeout=timeout)
        except queue.Empty:
            return None

    def send(self, message: pyigtl.MessageBase) -> bool:
        """Send a message to the server; False when not connected."""
        sock = self._sock
        if sock is None:
            return False
        data = message.pack()
        with self._send_lock:
            try:
                sock.settimeout(2.0)
                sock.sendall(data)
            except OSError:
                return False
            finally:
                with contextlib.suppress(OSError):
                    sock.settimeout(0.05)
        return True

    # -- thread ----------------------------------------------------------------------
    def _close(self) -> None:
        sock, self._sock = self._sock, None
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.close()

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                try:
                    self._receive_all()
                except _Closed:
                    pass
                self._emit(self.assembler.flush())
                self._close()
                if self._stop.is_set() or not self._reconnect():
                    break
        finally:
            self._ended.set()

    def _reconnect(self) -> bool:
        """Try to reconnect for ``reconnect_s`` seconds."""
        deadline = time.monotonic() + self.live.reconnect_s
        while not self._stop.is_set() and time.monotonic() < deadline:
            try:
                sock = connect(self.host, self.port, timeout=0.5)
            except BoneUSReconError:
                time.sleep(0.1)
                continue
            self._sock = sock
            self.counts["reconnects"] += 1
            return True
        return False

    def _receive_all(self) -> None:
        sock = self._sock
        assert sock is not None
        while not self._stop.is_set():
            header = _recv_exact(sock, HEADER_SIZE, self._stop)
            try:
                fields = pyigtl.MessageBase.parse_header(header)
            except (struct.error, UnicodeDecodeError):
                raise _Closed from None  # lost sync with the stream: reconnect
            size = int(fields["body_size"])
            if size > MAX_BODY:
                raise _Closed
            body = _recv_exact(sock, size, self._stop)
            self._handle(fields, body)

    def _handle(self, fields: dict[str, Any], body: bytes) -> None:
        kind = fields["message_type"]
        if kind not in ("IMAGE", "TRANSFORM"):
            self.counts["other"] += 1
            return
        msg = pyigtl.MessageBase.create_message(kind)
        try:
            msg.unpack(fields, body)
        except Exception:  # noqa: BLE001 (pyigtl raises struct.error, ValueError, NotImplementedError, ...)
            self.counts["malformed"] += 1
            return
        if kind == "TRANSFORM":
            self.counts["transforms"] += 1
            out = self.assembler.add_transform(
                msg.device_name, msg.matrix, msg.timestamp, _status(msg)
            )
        else:
            before = self.assembler.other_images
            out = self.assembler.add_image(
                msg.device_name, msg.image, msg.ijk_to_world_matrix, msg.timestamp
            )
            if self.assembler.other_images == before:
                self.counts["images"] += 1
        self._emit(out)

    def _emit(self, frames: list[PosedFrame]) -> None:
        for f in frames:
            try:
                self.queue.put_nowait(f)
            except queue.Full:
                self.counts["dropped"] += 1


def polydata_message(pd: vtkPolyData, name: str) -> pyigtl.PolyDataMessage:
    """A triangle mesh as an OpenIGTLink POLYDATA message (geometry; no point arrays)."""
    from vtkmodules.vtkCommonCore import vtkIdTypeArray

    pts = vtk_to_numpy(pd.GetPoints().GetData()).astype(np.float32)
    legacy = vtkIdTypeArray()
    pd.GetPolys().ExportLegacyFormat(legacy)
    polys = vtk_to_numpy(legacy).astype(np.uint32)
    return pyigtl.PolyDataMessage(points=pts, polygons=polys, device_name=name)


# ------------------------------------------------------------------------------------
# Server
# ------------------------------------------------------------------------------------
def open_listener(host: str, port: int) -> socket.socket:
    """A listening TCP socket, or a one-line error (port in use, not allowed)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    # No SO_REUSEADDR: a second server on a port already served must be refused.
    try:
        sock.bind((host, port))
        sock.listen(4)
    except OSError as exc:
        sock.close()
        import errno

        why = "already in use" if exc.errno == errno.EADDRINUSE else (exc.strerror or str(exc))
        raise BoneUSReconError(f"cannot listen: {why}", _where(host, port)) from None
    sock.settimeout(0.05)
    return sock


class SweepServer:
    """Replay a sweep over OpenIGTLink, frame by frame at a given rate.

    Parameters
    ----------
    sweep : Sweep
    host, port : str, int
        Where to listen (``127.0.0.1`` keeps it on this machine; ``0.0.0.0`` for all).
    fps : float
        Frames per second (default: the sweep's own rate from its timestamps, else 30).
    loop : bool
        Start again after the last frame (until stopped).
    mode : {"image", "transform", "plus"}
        ``image``: IMAGE ``Image_Reference`` carrying ``ImageToReference``.
        ``transform``: IMAGE ``Image`` in pixels plus TRANSFORM ``ImageToReference``.
        ``plus``: IMAGE ``Image`` plus ``ProbeToTracker`` and ``ReferenceToTracker``
        (identity) TRANSFORMs, with ``ImageToProbe`` = ``calibration``; the receiver
        needs the same calibration.
    calibration : ndarray (4, 4), optional
        ``ImageToProbe`` for ``mode="plus"``.

    Frames marked invalid in the sweep are sent as PLUS does: in the transform modes
    with ``TransformStatus`` ``INVALID`` metadata (OpenIGTLink 3 header), and not at
    all in ``image`` mode. Streaming starts when the first client connects and pauses
    while none is connected. Every message of a frame carries the frame's timestamp.
    """

    def __init__(
        self,
        sweep: Sweep,
        host: str = "127.0.0.1",
        port: int = 18944,
        *,
        fps: float | None = None,
        loop: bool = False,
        mode: str = "image",
        calibration: np.ndarray | None = None,
    ) -> None:
        if mode not in SERVE_MODES:
            raise BoneUSReconError(
                f"unknown serve mode {mode!r}; use one of {', '.join(SERVE_MODES)}"
            )
        if mode == "plus" and calibration is None:
            raise BoneUSReconError("serve mode 'plus' needs the ImageToProbe calibration")
        if fps is None:
            d = sweep.duration_s()
            fps = (sweep.n_valid - 1) / d if d > 0 and sweep.n_valid > 1 else 30.0
        if not 0 < fps <= 1000:
            raise BoneUSReconError(f"--fps must be in (0, 1000], got {fps}")
        self.sweep, self.fps, self.loop, self.mode = sweep, float(fps), loop, mode
        self.calibration = calibration
        self.host, self.port = host, int(port)
        self._listener = open_listener(host, int(port))
        self.port = self._listener.getsockname()[1]  # the real one when port 0 was asked
        self._clients: list[socket.socket] = []
        self._stop = threading.Event()
        #: Frames sent (counting each once, whatever the number of clients).
        self.sent = 0

    def stop(self) -> None:
        """Make :meth:`serve` return (from another thread or a signal handler)."""
        self._stop.set()

    def drop_clients(self) -> None:
        """Close every client connection (they may reconnect): a simulated outage."""
        for c in self._clients:
            with contextlib.suppress(OSError):
                c.close()
        self._clients.clear()

    def close(self) -> None:
        """Close the clients (after they have read everything) and the listening socket."""
        # Unread input at close() makes TCP reset the connection, which can discard
        # frames still in flight to the client: read it, half-close, wait for the
        # client to close its side (at most a second), then close. The listener goes
        # first, so that a client trying to reconnect is refused, not half-accepted.
        with contextlib.suppress(OSError):
            self._listener.close()
        self._discard_input()
        for c in self._clients:
            with contextlib.suppress(OSError):
                c.shutdown(socket.SHUT_WR)
        deadline = time.monotonic() + 1.0
        for c in self._clients:
            with contextlib.suppress(OSError):
                c.settimeout(max(0.01, deadline - time.monotonic()))
                while c.recv(1 << 16):
                    pass
        self.drop_clients()

    def _accept(self) -> None:
        # Wait for a client (the listener's 0.05 s) only while nobody is connected: with
        # clients, a waiting accept() before every frame held the replay to ~19 frames/s.
        self._listener.settimeout(0.0 if self._clients else 0.05)
        while True:
            try:
                c, _ = self._listener.accept()
            except (TimeoutError, BlockingIOError):
                return
            except OSError:
                return
            c.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            c.settimeout(5.0)
            self._clients.append(c)

    def _broadcast(self, data: bytes) -> None:
        for c in list(self._clients):
            try:
                c.sendall(data)
            except OSError:
                with contextlib.suppress(OSError):
                    c.close()
                self._clients.remove(c)

    def _discard_input(self) -> None:
        """Read and ignore what clients send (e.g. the surface), so they never block."""
        for c in list(self._clients):
            with contextlib.suppress(OSError):
                c.setblocking(False)
                try:
                    while c.recv(1 << 16):
                        pass
                except (BlockingIOError, InterruptedError):
                    pass
                finally:
                    c.settimeout(5.0)

    def frame_messages(self, k: int, timestamp: float) -> bytes:
        """The packed messages of frame ``k`` (empty when nothing is sent for it)."""
        sw = self.sweep
        valid = bool(sw.valid[k])
        image = np.asarray(sw.frames[k], dtype=np.uint8)[None]
        pose = sw.image_to_reference[k]
        if self.mode == "image":
            if not valid:
                return b""
            msgs: list[pyigtl.MessageBase] = [
                pyigtl.ImageMessage(
                    image,
                    ijk_to_world_matrix=pose,
                    world_coordinate_system="ras",
                    timestamp=timestamp,
                    device_name="Image_Reference",
                )
            ]
        else:
            if self.mode == "transform":
                tr = {"ImageToReference": pose}
            else:
                assert self.calibration is not None
                tr = {
                    "ProbeToTracker": pose @ np.linalg.inv(self.calibration),
                    "ReferenceToTracker": np.eye(4),
                }
            msgs = []
            for name, m in tr.items():
                t = pyigtl.TransformMessage(m, timestamp=timestamp, device_name=name)
                t.header_version = 2  # OpenIGTLink 3: carries the status as metadata
                t.metadata = {"TransformStatus": "OK" if valid else "INVALID"}
                msgs.append(t)
            msgs.append(
                pyigtl.ImageMessage(
                    image,
                    ijk_to_world_matrix=np.eye(4),
                    world_coordinate_system="ras",
                    timestamp=timestamp,
                    device_name="Image",
                )
            )
        return b"".join(m.pack() for m in msgs)

    def serve(self, on_frame: Callable[[int], None] | None = None) -> int:
        """Stream the sweep until done (or stopped); returns the number of frames sent.

        Parameters
        ----------
        on_frame : callable, optional
            Called with the number of frames sent so far after each frame.
        """
        n = self.sweep.n_frames
        period = 1.0 / self.fps
        base = time.time()
        k = 0
        next_t = None
        try:
            while not self._stop.is_set():
                self._accept()
                if not self._clients:
                    next_t = None
                    time.sleep(0.02)
                    continue
                now = time.monotonic()
                if next_t is None:
                    next_t = now
                if now < next_t:
                    time.sleep(min(next_t - now, 0.05))
                    continue
                self._discard_input()
                ts = base + self.sent * period
                data = self.frame_messages(k, ts)
                if data:
                    self._broadcast(data)
                self.sent += 1
                if on_frame is not None:
                    on_frame(self.sent)
                next_t += period
                k += 1
                if k == n:
                    if not self.loop:
                        break
                    k = 0
        finally:
            self.close()
        return self.sent
