"""One client's conversation with the server, without sockets: bytes in, replies out.

Requests a client may send (any header version 1 or 2; device names are case-sensitive):

- ``POINT`` (any device name, e.g. ``"Markers"``): the n_d marker positions in mm, in the
  model's marker order, in the tracker frame of the registration (or the client frame when
  none is set: the model's LPS frame unless the server says RAS). Reply: ``POLYDATA "TissueSurface"``. With a
  model that supports missing markers (trained with marker dropout, or a
  :class:`~tissuecast.surrogate.robust.SubModelSet`), a point whose coordinates are all
  NaN marks an untracked marker; otherwise NaN/inf is an error.
- ``TRANSFORM "Marker0"`` ... ``"Marker{n_d-1}"`` (0-based, model marker order; PLUS-style
  names such as ``"Marker0ToTracker"`` are accepted too): one marker each; the translation
  column is the marker position (mm, tracker/client frame), the rotation is ignored. In ``"frame"``
  mode (default) a prediction is made once every marker has been updated since the
  previous prediction (one mesh per tracker frame); in ``"each"`` mode every update after
  the first complete set triggers a prediction with the latest position of every marker.
- ``TRANSFORM "<From>To<Target>"`` such as ``TrackerToRas``, ``ReferenceToRas``,
  ``TrackerToImage``: the registration from the tracker's frame to RAS (3D Slicer's world)
  or to the image (the model's LPS frame); later marker positions are mapped by it before
  prediction and replies are sent in the target frame (see :mod:`tissuecast.serve.client_frames`;
  shared by every connection of the server). No reply.
- ``TRANSFORM "<device>"`` of a tracked instrument the model reads (``RetractorTipToRef``,
  ``scenario.instruments[k].device``): the tool's pose in the tracker frame (translation = tool
  tip, mm; third column = push direction), mapped like the markers; every later prediction
  uses it until it is ``serve.instrument_timeout`` seconds old (:mod:`tissuecast.serve.instruments`).
  No reply. When an instrument is lost (or not tracked at the first prediction) the prediction
  is made from the markers only and followed by a STATUS ``InstrumentLost``; a STATUS
  ``InstrumentTracked`` follows the first prediction with it again.
- ``GET_POLYDATA "TissueField"``: the full vertex field of this client's latest prediction
  (``POLYDATA "TissueField"``); ``GET_POLYDATA "TissueSurface"`` (or no device name)
  repeats the latest surface.

With ``full_field=True`` every prediction is answered by both messages, surface first.
With a calibrated model, a prediction that raises the out-of-distribution alarm is followed
by a ``STATUS "TissueStatus"`` message (:mod:`tissuecast.serve.status`); the first clean
prediction after an alarm is followed by a STATUS ``OK``. Marker positions the model's input
gate refuses (:mod:`tissuecast.surrogate.gate`: a non-finite marker, one displaced far beyond
the simulations, markers at distances the body cannot take) get no mesh: a STATUS
``InputRefused`` naming the marker, then the ``STRING "ERROR"`` below; the next accepted
prediction is followed by a STATUS ``OK``.
Anything else gets a ``STRING "ERROR"`` reply whose text says what was wrong; the
connection stays open unless the byte stream can no longer be trusted (oversized body,
unknown header version, garbage header), in which case the error is sent and the session
asks to be closed.
"""

from __future__ import annotations

import logging
import re
from collections import Counter
from collections.abc import Callable

import numpy as np

from ..config import TRANSFORM_MODES, ServeConfig
from ..frames import FrameError
from .client_frames import REGISTRATION_PATTERN, ClientFrames
from .instruments import LOST_NAME, TRACKED_NAME, InstrumentTracking
from .predictor import FIELD_DEVICE, SURFACE_DEVICE, InputRefused, Prediction, PredictionError, SurfacePredictor
from .protocol import (
    DEFAULT_MAX_BODY_BYTES,
    HEADER_SIZE,
    Header,
    ProtocolError,
    decode_points,
    decode_transform,
    message_content,
    pack_string,
    parse_header,
)

__all__ = ["ClientSession", "ERROR_DEVICE", "MARKER_PREFIX", "TRANSFORM_MODES"]

log = logging.getLogger(__name__)

ERROR_DEVICE = "ERROR"
MARKER_PREFIX = "Marker"


class ClientSession:
    """The protocol state of one connection.

    Args:
        predictor: the shared :class:`SurfacePredictor`.
        emit: called with each reply (bytes-like); it must send or copy the data before
            returning, because replies alias the predictor's reusable buffers.
        full_field: also send ``TissueField`` after every ``TissueSurface``.
        transform_mode: ``"frame"`` or ``"each"`` (see the module docstring).
        max_body_bytes: bodies announced larger than this close the connection unread.
        frames: the (shared) :class:`ClientFrames`; None = a private one, everything in the
            model's LPS frame.
        instruments: the (shared) :class:`~.instruments.InstrumentTracking` of the model's
            instruments; None = a private one with the default timeout.

    Attributes:
        close_reason: None while the connection is usable, else why it must be closed.
        counts: Counter of handled events (``"requests"``, ``"replies"``, ``"errors"``...).
    """

    def __init__(
        self,
        predictor: SurfacePredictor,
        emit: Callable[[bytes | memoryview], None],
        *,
        full_field: bool = ServeConfig.full_field,
        transform_mode: str = ServeConfig.transform_mode,
        max_body_bytes: int = DEFAULT_MAX_BODY_BYTES,
        frames: ClientFrames | None = None,
        instruments: InstrumentTracking | None = None,
    ):
        if transform_mode not in TRANSFORM_MODES:
            raise ValueError(f"transform_mode must be one of {TRANSFORM_MODES}, got {transform_mode!r}")
        self.predictor = predictor
        self.emit = emit
        self.full_field = bool(full_field)
        self.transform_mode = transform_mode
        self.max_body_bytes = int(max_body_bytes)
        self.frames = frames if frames is not None else ClientFrames()
        self.instruments = instruments if instruments is not None else InstrumentTracking(
            predictor.instrument_devices, predictor.reference_surface)
        self._tracked: dict[str, bool] = {}  # what this connection was last told of each instrument
        self.close_reason: str | None = None
        self.counts: Counter = Counter()
        self.last: Prediction | None = None
        self._buffer = bytearray()
        self._header: Header | None = None
        n = predictor.n_markers
        self._positions = predictor.reference.copy()
        self._seen = np.zeros(n, dtype=bool)
        self._fresh = np.zeros(n, dtype=bool)
        self._stamps = np.zeros(n)
        self._alarmed = False
        self._marker_re = re.compile(rf"{MARKER_PREFIX}(0|[1-9][0-9]*)(To[A-Za-z0-9_]+)?")

    @property
    def partial(self) -> bool:
        """True while an incomplete message sits in the buffer."""
        return bool(self._buffer) or self._header is not None

    def feed(self, data: bytes | memoryview, budget: int | None = None) -> bool:
        """Consume received bytes; replies go to ``emit``. Never raises for bad input.

        Args:
            data: the bytes received.
            budget: handle at most this many complete messages now (None: all).

        Returns:
            True when complete messages were left unhandled (call :meth:`process` later).
        """
        if self.close_reason is None:
            self._buffer += data
        return self.process(budget)

    def process(self, budget: int | None = None) -> bool:
        """Handle up to ``budget`` buffered complete messages; True if the budget ran out first."""
        buf = self._buffer
        handled = 0
        while self.close_reason is None:
            if self._header is None:
                if len(buf) < HEADER_SIZE:
                    return False
                if budget is not None and handled >= budget:
                    return True
                try:
                    self._header = parse_header(bytes(buf[:HEADER_SIZE]), self.max_body_bytes)
                except ProtocolError as exc:
                    self._fatal(str(exc), timestamp=0.0)
                    return False
                del buf[:HEADER_SIZE]
            header = self._header
            if len(buf) < header.body_size:
                return False
            if budget is not None and handled >= budget:
                return True
            body = bytes(buf[: header.body_size])
            del buf[: header.body_size]
            self._header = None
            self._handle(header, body)
            handled += 1
        return False

    # ------------------------------------------------------------------ messages
    def _handle(self, header: Header, body: bytes) -> None:
        self.counts["requests"] += 1
        try:
            content = message_content(header, body)
            kind = header.message_type
            if kind == "POINT":
                positions = decode_points(header, content, allow_missing=self.predictor.supports_missing,
                                          check_finite=self.predictor.gate is None)
                self._serve(positions, header.timestamp)
            elif kind == "TRANSFORM":
                self._on_transform(header, decode_transform(header, content))
            elif kind == "GET_POLYDATA":
                self._on_get(header)
            else:
                raise ProtocolError(
                    f"unsupported message type {kind!r} (device {header.device_name!r}); this server "
                    f"accepts POINT, TRANSFORM {MARKER_PREFIX}0..{MARKER_PREFIX}{self.predictor.n_markers - 1} "
                    f"and GET_POLYDATA {FIELD_DEVICE}/{SURFACE_DEVICE}"
                )
        except InputRefused as exc:
            self._refused(exc, header.timestamp)
        except (ProtocolError, PredictionError, FrameError) as exc:
            self._error(str(exc), header.timestamp)

    def _on_transform(self, header: Header, matrix: np.ndarray) -> None:
        if self.predictor.is_instrument(header.device_name):
            try:
                self.instruments.update(header.device_name, self.frames.tracker_to_model @ matrix)
            except ValueError as exc:
                raise ProtocolError(f"TRANSFORM {header.device_name!r}: {exc}") from exc
            self.counts["instrument_poses"] += 1
            return
        match = self._marker_re.fullmatch(header.device_name)
        index = int(match.group(1)) if match else -1
        if not 0 <= index < self.predictor.n_markers:
            if REGISTRATION_PATTERN.fullmatch(header.device_name):
                self.frames.set_from_message(header.device_name, matrix)
                self.counts["registrations"] += 1
                log.info("registration %s: %s", header.device_name, self.frames.describe())
                return
            raise ProtocolError(
                f"TRANSFORM device {header.device_name!r} is not a marker ({MARKER_PREFIX}0.."
                f"{MARKER_PREFIX}{self.predictor.n_markers - 1}, model marker order) and not a registration "
                "(<From>To<Target>, e.g. TrackerToRas, ReferenceToRas, TrackerToImage)"
                + (f" or an instrument ({', '.join(self.predictor.instrument_devices)})"
                   if self.predictor.instrument_devices else "")
            )
        self._positions[index] = matrix[:3, 3]
        self._seen[index] = self._fresh[index] = True
        self._stamps[index] = header.timestamp
        ready = self._fresh.all() if self.transform_mode == "frame" else self._seen.all()
        if ready:
            self._fresh[:] = False
            self._serve(self._positions.copy(), float(self._stamps.max()))

    def _on_get(self, header: Header) -> None:
        if header.device_name not in ("", FIELD_DEVICE, SURFACE_DEVICE):
            raise ProtocolError(f"GET_POLYDATA for unknown device {header.device_name!r}; use {FIELD_DEVICE} or {SURFACE_DEVICE}")
        if self.last is None:
            raise ProtocolError("no prediction yet on this connection: send marker positions first")
        if header.device_name == FIELD_DEVICE:
            self._send(self.predictor.field_message(self.last, self.frames))
        else:
            self._send(self.predictor.surface_message(self.last, self.frames))

    def _serve(self, positions: np.ndarray, timestamp: float) -> None:
        poses = self.instruments.current()
        # the mesh and its bounds go out first; the alarm, which reads the inputs (markers and
        # instruments) and not the field, follows
        prediction = self.predictor.predict(self.frames.to_model(positions), timestamp, instruments=poses, alarm=False)
        self.last = prediction
        self.counts["predictions"] += 1
        self._send(self.predictor.surface_message(prediction, self.frames))
        if self.full_field:
            self._send(self.predictor.field_message(prediction, self.frames))
        self._send_instrument_status(poses, timestamp)
        prediction = self.last = self.predictor.with_alarm(prediction)  # a failure: STRING ERROR after the mesh
        if prediction.alarm is not None and (prediction.alarm.raised or self._alarmed):
            self._send_alarm_status(prediction)
        elif self._alarmed:  # a refusal before, a model without alarm now: clear it
            from .status import StatusCode, pack_status

            self._alarmed = False
            self.counts["alarms_cleared"] += 1
            self.send(pack_status(StatusCode.OK, 0, "", "marker input accepted", prediction.timestamp))

    def _send_instrument_status(self, poses: dict, timestamp: float) -> None:
        """A STATUS for each instrument whose tracking changed since this connection was last told."""
        from .status import StatusCode, pack_status

        for name, pose in poses.items():
            tracked = pose is not None
            if self._tracked.get(name) == tracked:
                continue
            self._tracked[name] = tracked
            self.counts["instrument_tracked" if tracked else "instrument_lost"] += 1
            if tracked:
                self.send(pack_status(StatusCode.OK, 0, TRACKED_NAME, self.instruments.tracked_text(name), timestamp))
            else:
                log.info("instrument %s lost: predicting from the markers only", name)
                self.send(pack_status(StatusCode.TIME_OUT, 0, LOST_NAME, self.instruments.lost_text(name), timestamp))

    def send(self, data) -> None:
        """Send an extra packed message on this connection (e.g. a STATUS); counted as a reply."""
        self._send(data)

    def _send_alarm_status(self, prediction: Prediction) -> None:
        from .status import ALARM_NAME, AlarmBits, StatusCode, pack_status

        alarm = prediction.alarm
        self._alarmed = bool(alarm.raised)
        self.counts["alarms" if alarm.raised else "alarms_cleared"] += 1
        if alarm.raised:
            bits = (AlarmBits.FAR_FROM_TRAINING if alarm.far_from_training else 0) | (
                AlarmBits.INCONSISTENT_MARKERS if alarm.inconsistent_markers else 0) | (
                AlarmBits.STILL_MARKER if alarm.still_marker_alarm else 0) | (
                AlarmBits.SWAPPED_MARKERS if alarm.swapped_markers_alarm else 0)
            self.send(pack_status(StatusCode.UNKNOWN_ERROR, int(bits), ALARM_NAME, alarm.text, prediction.timestamp))
        else:
            self.send(pack_status(StatusCode.OK, 0, "", alarm.text, prediction.timestamp))

    def _refused(self, exc: InputRefused, timestamp: float) -> None:
        """Markers the input gate refuses: no mesh; a STATUS ``InputRefused`` (subcode: why) and
        the ``STRING "ERROR"`` every rejected request gets; the next prediction sends STATUS OK."""
        from .status import REFUSED_NAME, StatusCode, pack_status, refusal_bits

        self.counts["refused"] += 1
        self._alarmed = True
        self.send(pack_status(StatusCode.UNKNOWN_ERROR, refusal_bits(exc.verdict.reason), REFUSED_NAME, str(exc), timestamp))
        self._error(str(exc), timestamp)

    # ------------------------------------------------------------------ replies
    def _send(self, data) -> None:
        self.counts["replies"] += 1
        self.emit(data)

    def _error(self, text: str, timestamp: float) -> None:
        self.counts["errors"] += 1
        log.debug("rejected message: %s", text)
        self._send(pack_string(ERROR_DEVICE, text, timestamp))

    def _fatal(self, text: str, timestamp: float) -> None:
        self._error(text, timestamp)
        self.close_reason = text
        self._buffer.clear()
        self._header = None
