"""The OpenIGTLink server: one ``selectors`` event loop, non-blocking sockets, many clients.

The loop never waits on one client: it reads whatever bytes have arrived, lets the client's
:class:`~tissuecast.serve.session.ClientSession` answer every complete message at once
(predictions are short next to a network round trip, see docs/serving.md) and sends replies
without blocking; what a slow reader does not take is queued for that client only. Per-client limits keep one bad
peer from hurting the others:

- a body announced larger than ``max_body_bytes`` closes the connection unread;
- a message left incomplete for more than ``client_timeout`` seconds closes it;
- more than ``max_output_bytes`` of unsent replies (a client that stops reading) closes it;
- any unexpected exception while serving a client is logged and closes that client only.

The server binds to ``serve.host`` (127.0.0.1, this machine only) unless another host is
given. Connections and disconnections are logged (logger ``tissuecast.serve.server``, level INFO).
"""

from __future__ import annotations

import logging
import selectors
import socket
import threading
import time
from collections import Counter

from ..config import ServeConfig
from ..surrogate.field_predictor import FieldPredictor
from .client_frames import ClientFrames
from .instruments import InstrumentTracking
from .predictor import SurfacePredictor
from .protocol import DEFAULT_MAX_BODY_BYTES, pack_string
from .session import ERROR_DEVICE, ClientSession

__all__ = ["IGTLServer"]

log = logging.getLogger(__name__)

#: Unsent reply bytes tolerated per client before it is dropped as not reading: ~100 full
#: fields of a 10k-vertex mesh, far more than a live reader ever leaves queued.
MAX_OUTPUT_BYTES = 32 << 20
#: Simultaneous connections (an operating room has a handful: Slicer, PLUS, a recorder).
MAX_CLIENTS = 64
#: Complete messages answered per client before the others get a turn.
MESSAGES_PER_TURN = 16
#: Connections the kernel queues before they are accepted (as many as the clients served).
LISTEN_BACKLOG = MAX_CLIENTS
#: Bytes read per receive: a few thousand POINT messages, so a pipelining client is drained
#: in a few calls while one read stays small next to the replies' buffers.
RECV_BYTES = 1 << 18
#: Longest wait (s) of the event loop when no client has an incomplete message (stop() and
#: new data wake it at once; this only bounds how late an idle loop looks again).
IDLE_POLL_S = 1.0
#: Bytes read per call while draining the wake-up socket (each stop() writes one).
WAKE_DRAIN_BYTES = 512


class _Client:
    __slots__ = ("sock", "peer", "session", "out", "partial_since", "closing", "dead", "backlog")

    def __init__(self, sock: socket.socket, peer: str):
        self.sock = sock
        self.peer = peer
        self.session: ClientSession | None = None
        self.out = bytearray()
        self.partial_since: float | None = None
        self.closing: str | None = None  # why to close once the queued replies are flushed
        self.dead: str | None = None
        self.backlog = False  # complete messages wait in the session buffer (fair turn-taking)


class IGTLServer:
    """Serve a deformation model over OpenIGTLink (see :mod:`tissuecast.serve.session`).

    Args:
        model: a :class:`~tissuecast.surrogate.field_predictor.FieldPredictor` (e.g. a DeformationModel)
            or a ready :class:`SurfacePredictor`.
        host: bind address; keep 127.0.0.1 unless other machines must connect.
        port: TCP port; 0 picks a free one (read it from :attr:`address`).
        full_field: answer every prediction with the full field as well.
        transform_mode: ``"frame"`` or ``"each"`` (TRANSFORM input, see session).
        max_body_bytes: largest accepted message body.
        client_timeout: seconds an incomplete message may wait for its remaining bytes.
        max_output_bytes: unsent reply bytes tolerated per client.
        max_clients: simultaneous connections; further ones get an error and are closed.
        max_marker_offset: mm, see :class:`SurfacePredictor`.
        messages_per_turn: complete messages handled per client before the others get a
            turn (a client pipelining many requests cannot starve the rest).
        frames: the :class:`~tissuecast.serve.client_frames.ClientFrames` shared by all
            connections (None: everything in the model's LPS frame until a registration
            TRANSFORM arrives).
        instrument_timeout: seconds after its last TRANSFORM a tracked instrument counts as
            lost (the model then predicts from the markers only; :mod:`.instruments`).
    """

    def __init__(
        self,
        model: FieldPredictor | SurfacePredictor,
        host: str = ServeConfig.host,
        port: int = ServeConfig.port,
        *,
        full_field: bool = ServeConfig.full_field,
        transform_mode: str = ServeConfig.transform_mode,
        max_body_bytes: int = DEFAULT_MAX_BODY_BYTES,
        client_timeout: float = ServeConfig.client_timeout,
        max_output_bytes: int = MAX_OUTPUT_BYTES,
        max_clients: int = MAX_CLIENTS,
        max_marker_offset: float = ServeConfig.max_marker_offset,
        messages_per_turn: int = MESSAGES_PER_TURN,
        frames: ClientFrames | None = None,
        method: str = ServeConfig.method,
        instrument_timeout: float = ServeConfig.instrument_timeout,
    ):
        if isinstance(model, SurfacePredictor):
            self.predictor = model
        else:
            self.predictor = SurfacePredictor(model, max_marker_offset=max_marker_offset, method=method)
        self.frames = frames if frames is not None else ClientFrames()
        self.instruments = InstrumentTracking(self.predictor.instrument_devices, self.predictor.reference_surface,
                                              instrument_timeout)
        self._session_options = dict(full_field=full_field, transform_mode=transform_mode, max_body_bytes=max_body_bytes,
                                     frames=self.frames, instruments=self.instruments)
        ClientSession(self.predictor, lambda data: None, **self._session_options)  # validate options now
        self.client_timeout = float(client_timeout)
        self.max_output_bytes = int(max_output_bytes)
        self.max_clients = int(max_clients)
        self.messages_per_turn = max(1, int(messages_per_turn))
        self.stats: Counter = Counter()
        self._listener = socket.create_server((host, port), backlog=LISTEN_BACKLOG)
        self._listener.setblocking(False)
        self.address: tuple[str, int] = self._listener.getsockname()[:2]
        self._selector = selectors.DefaultSelector()
        self._selector.register(self._listener, selectors.EVENT_READ, None)
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._selector.register(self._wake_r, selectors.EVENT_READ, "wake")
        self._clients: dict[int, _Client] = {}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._closed = False
        log.info("OpenIGTLink server listening on %s:%d", *self.address)

    @classmethod
    def from_config(cls, model: FieldPredictor | SurfacePredictor, config: ServeConfig, **options) -> "IGTLServer":
        """A server set up as a ``[serve]`` config section says (host, port, full_field,
        transform_mode, client_timeout, max_marker_offset, client_frame, tracker_to_client, method,
        instrument_timeout); ``options`` (any argument of the constructor) take precedence."""
        settings = dict(full_field=config.full_field, transform_mode=config.transform_mode,
                        client_timeout=config.client_timeout, max_marker_offset=config.max_marker_offset,
                        method=config.method, instrument_timeout=config.instrument_timeout)
        settings.update(options)
        if "frames" not in settings:
            settings["frames"] = ClientFrames(config.client_frame, config.tracker_to_client or None)
        host, port = settings.pop("host", config.host), settings.pop("port", config.port)
        return cls(model, host, port, **settings)

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> "IGTLServer":
        """Run the event loop in a daemon thread and return immediately."""
        if self._thread is None:
            self._thread = threading.Thread(target=self.serve_forever, name="tissuecast-igtl", daemon=True)
            self._thread.start()
        return self

    def serve_forever(self) -> None:
        """Run the event loop in this thread until :meth:`stop` is called."""
        try:
            while not self._stop.is_set():
                backlog = [c for c in self._clients.values() if c.backlog]
                for key, mask in self._selector.select(timeout=0.0 if backlog else self._poll_timeout()):
                    if key.data is None:
                        self._accept()
                    elif key.data == "wake":
                        self._drain_wake()
                    else:
                        self._service(key.data, mask)
                for client in backlog:
                    if self._clients.get(client.sock.fileno()) is client and client.backlog:
                        self._service(client, 0)
                self._expire()
        finally:
            self._shutdown()

    def stop(self, timeout: float = 5.0) -> None:
        """Stop the loop, close every connection and the listening socket."""
        self._stop.set()
        try:
            self._wake_w.send(b"x")
        except OSError:
            pass
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout)
        elif self._thread is None:
            self._shutdown()

    def __enter__(self) -> "IGTLServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def n_clients(self) -> int:
        return len(self._clients)

    # ------------------------------------------------------------------ loop parts
    def _poll_timeout(self) -> float:
        pending = [c.partial_since for c in self._clients.values() if c.partial_since is not None]
        if not pending:
            return IDLE_POLL_S
        return max(0.0, min(IDLE_POLL_S, min(pending) + self.client_timeout - time.monotonic()))

    def _drain_wake(self) -> None:
        try:
            while self._wake_r.recv(WAKE_DRAIN_BYTES):
                pass
        except BlockingIOError:
            pass

    def _accept(self) -> None:
        while True:
            try:
                sock, addr = self._listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:  # e.g. too many open files: keep serving the others
                log.warning("accept failed: %s", exc)
                return
            peer = f"{addr[0]}:{addr[1]}" if isinstance(addr, tuple) else str(addr)
            sock.setblocking(False)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self.stats["connections"] += 1
            if len(self._clients) >= self.max_clients:
                log.warning("refusing %s: %d clients already connected", peer, len(self._clients))
                try:
                    sock.send(pack_string(ERROR_DEVICE, f"server busy: {self.max_clients} clients connected"))
                except OSError:
                    pass
                sock.close()
                self.stats["refused"] += 1
                self.stats["disconnections"] += 1
                continue
            client = _Client(sock, peer)
            client.session = ClientSession(self.predictor, lambda data, c=client: self._emit(c, data), **self._session_options)
            self._clients[sock.fileno()] = client
            self._selector.register(sock, selectors.EVENT_READ, client)
            log.info("client %s connected (%d connected)", peer, len(self._clients))

    def _service(self, client: _Client, mask: int) -> None:
        try:
            if mask & selectors.EVENT_WRITE:
                self._flush(client)
            if client.backlog and client.dead is None and not client.closing:
                self._session_turn(client, client.session.process(self.messages_per_turn))
            elif mask & selectors.EVENT_READ and client.dead is None and not client.closing:
                self._read(client)
        except Exception as exc:  # one client's failure must not stop the server
            log.exception("error while serving %s", client.peer)
            self.stats["internal_errors"] += 1
            client.dead = client.dead or f"internal error: {type(exc).__name__}: {exc}"
        if client.dead is not None or (client.closing and not client.out):
            self._drop(client, client.dead or client.closing)

    def _read(self, client: _Client) -> None:
        try:
            data = client.sock.recv(RECV_BYTES)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            client.dead = f"receive failed: {exc}"
            return
        if not data:
            self._close_after_flush(client, "peer closed the connection")
            return
        self.stats["bytes_in"] += len(data)
        self._session_turn(client, client.session.feed(data, self.messages_per_turn))

    def _session_turn(self, client: _Client, more: bool) -> None:
        session = client.session
        client.backlog = more and session.close_reason is None
        if session.close_reason is not None:
            self.stats["protocol_closes"] += 1
            self._close_after_flush(client, session.close_reason)
            return
        waiting = session.partial and not client.backlog  # an incomplete message waits for its bytes
        client.partial_since = (client.partial_since or time.monotonic()) if waiting else None

    def _close_after_flush(self, client: _Client, reason: str) -> None:
        client.closing = reason
        # a peer that does not take its last replies is dropped after client_timeout
        client.partial_since = time.monotonic() if client.out else None
        if client.out:  # stop watching for input (EOF would keep the socket readable)
            self._selector.modify(client.sock, selectors.EVENT_WRITE, client)

    def _emit(self, client: _Client, data) -> None:
        if client.dead is not None:
            return
        self.stats["replies"] += 1
        sent = 0
        if not client.out:
            try:
                sent = client.sock.send(data)
            except (BlockingIOError, InterruptedError):
                sent = 0
            except OSError as exc:
                client.dead = f"send failed: {exc}"
                return
        if sent < len(data):
            client.out += data[sent:]
            if len(client.out) > self.max_output_bytes:
                client.dead = f"more than {self.max_output_bytes} bytes of replies left unread"
                return
            self._selector.modify(client.sock, selectors.EVENT_READ | selectors.EVENT_WRITE, client)

    def _flush(self, client: _Client) -> None:
        try:
            sent = client.sock.send(client.out)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            client.dead = f"send failed: {exc}"
            return
        del client.out[:sent]
        if not client.out:
            self._selector.modify(client.sock, selectors.EVENT_READ, client)

    def _expire(self) -> None:
        now = time.monotonic()
        for client in list(self._clients.values()):
            if client.partial_since is not None and now - client.partial_since > self.client_timeout:
                self.stats["timeouts"] += 1
                self._drop(client, f"incomplete message for more than {self.client_timeout:g} s")

    def _drop(self, client: _Client, reason: str) -> None:
        fd = client.sock.fileno()
        if fd not in self._clients:
            return
        # count before removing, so an observer that sees n_clients drop also sees the count
        self.stats["disconnections"] += 1
        del self._clients[fd]
        try:
            self._selector.unregister(client.sock)
        except (KeyError, ValueError):
            pass
        client.sock.close()
        counts = client.session.counts
        log.info(
            "client %s disconnected (%s); %d requests, %d predictions, %d errors",
            client.peer, reason, counts["requests"], counts["predictions"], counts["errors"],
        )

    def _shutdown(self) -> None:
        if self._closed:
            return
        self._closed = True
        for client in list(self._clients.values()):
            self._drop(client, "server stopped")
        for sock in (self._listener, self._wake_r, self._wake_w):
            try:
                self._selector.unregister(sock)
            except (KeyError, ValueError):
                pass
            sock.close()
        self._selector.close()
        log.info("OpenIGTLink server on %s:%d stopped", *self.address)
