"""Grab: the source stage. Frames from the simulator, a session folder, an MCAP recording or
a live camera, as ``raw`` messages (plus ``truth`` from the simulator, which no stage reads).

Sources (parameter ``source``):

- ``sim``: the Kinect v2 simulator (``gaitflow.sim``), one bundled walking trial (``trial``)
  rendered with ``seed``; yields ``[RawFrame, GroundTruth]`` per frame.
- ``session``: a session folder (``shared/spec/session-folder.md``) at ``path``; yields
  ``[RawFrame]`` per frame with the original timestamps (gaps stay gaps).
- ``mcap``: a recording made by ``gaitflow record`` at ``path``; replays its ``raw`` (and
  ``truth``, if recorded) messages in file order.
- ``kinect2``, ``k4a``, ``realsense``: a live camera through ``gaitflow.drivers``.

Each item the source yields is the list of messages of one camera frame. Headers carry
trial (the recording name), frame (the index), capture_ns and ``last=True`` on the final
frame of each trial; the runtime paces publication by capture_ns or runs flat out.

Bad input: a missing or malformed file (camera.json, any selected frames.csv, the MCAP
file) raises :class:`InputError` naming it when the source opens, before any frame goes
out; a single bad frame is skipped, counted in :attr:`GrabSource.counters` and logged.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

from gaitflow.schemas import GroundTruth, Message, RawFrame, decode, peek_header
from gaitflow.stages.base import SourceSpec

from gaitflow.errors import InputError, SchemaError
from gaitflow.params import Param, ParamSet
from gaitflow.session import PROTOCOL, SessionReader, iter_raw_frames, recording_order

log = logging.getLogger("gaitflow.grab")

SOURCES = ("sim", "session", "mcap", "kinect2", "k4a", "realsense")
LIVE = ("kinect2", "k4a", "realsense")
# On a loop the capture clock keeps running: the next pass starts one frame period after
# the previous one ended (the Kinect v2's 30 fps when the source does not say).
DEFAULT_PERIOD_NS = 33_333_333

PARAMS = ParamSet(
    "grab",
    (
        Param("source", str, "sim", "", "where frames come from", choices=SOURCES),
        Param("path", str, "", "", "session folder (session) or .mcap file (mcap)"),
        Param("trial", str, "", "", "sim: bundled walking trial (empty = the first one bundled)"),
        Param("seed", int, 0, "", "sim: random seed (output is deterministic per seed)", low=0),
        Param("camera", str, "cam0", "", "camera id stamped on every message"),
        Param(
            "recordings",
            str,
            "",
            "",
            "comma-separated recordings to play, in protocol order (empty = all); "
            "live sources: the trial name to stamp (default walk-01)",
        ),
        Param("loop", bool, False, "", "replay forever (capture times keep increasing)"),
        Param("quick", bool, False, "", "sim: short protocol durations (SimConfig.quick)"),
        Param("max_frames", int, 0, "frames", "stop after this many frames (0 = all)", low=0),
    ),
)


def _restamp(msg: Message, **changes: Any) -> Message:
    """The message with header fields replaced (arrays are shared, not copied)."""
    hdr = msg.header
    if all(getattr(hdr, k) == v for k, v in changes.items()):
        return msg
    return dataclasses.replace(msg, header=dataclasses.replace(hdr, **changes))


def _selected(spec: str) -> list[str]:
    return [s.strip() for s in spec.split(",") if s.strip()]


class GrabSource:
    """Iterator over frames (lists of messages) with counters of what was skipped.

    ``counters`` maps a reason to a count (for a session folder: missing, unreadable,
    not_16bit, not_single_channel, wrong_size; for MCAP: bad_payload); ``warnings`` holds
    one line per skipped frame (bounded).
    """

    def __init__(self, params: dict[str, Any]) -> None:
        self.params = params
        self.counters: dict[str, int] = {}
        self.warnings: list[str] = []
        self.frames = 0
        # The source's camera.json document where it has one (session folder, simulator,
        # live camera); None for MCAP replays. Downstream stages take intrinsics from it.
        self.camera_doc: dict[str, Any] | None = None
        self._driver: Any = None
        # Open (and check) the input now, so bad input fails before the first frame.
        self._it = self._run(self._opener())

    def __iter__(self) -> GrabSource:
        return self

    def __next__(self) -> list[Message]:
        return next(self._it)

    def close(self) -> None:
        """Stop the source (releases a live camera, even if no frame was read)."""
        self._it.close()
        if self._driver is not None:
            self._driver.close()

    def _count(self, reason: str, line: str) -> None:
        self.counters[reason] = self.counters.get(reason, 0) + 1
        if len(self.warnings) < 200:
            self.warnings.append(line)
        log.warning("grab: %s", line)

    # ----------------------------------------------------------------- the loop

    def _run(self, make: Callable[[], Iterator[list[Message]]]) -> Iterator[list[Message]]:
        p = self.params
        # Live frames go out at once; replayed ones get the final-frame flag by look-ahead.
        mark = (lambda g: g) if p["source"] in LIVE else _mark_last
        limit = p["max_frames"]
        offset = 0
        while True:
            first_ns = last_ns = None
            period = DEFAULT_PERIOD_NS
            for group in mark(make()):
                ts = group[0].header.capture_ns
                if first_ns is None:
                    first_ns = ts
                elif last_ns is not None and ts > last_ns:
                    period = min(period, ts - last_ns)
                last_ns = ts
                if offset:
                    group = [_restamp(m, capture_ns=m.header.capture_ns + offset) for m in group]
                self.frames += 1
                if limit and self.frames >= limit:
                    yield [_restamp(m, last=True) for m in group]
                    return
                yield group
            if self.counters:
                total = sum(self.counters.values())
                log.warning("grab: %d frame(s) skipped so far: %s", total, self.counters)
            if not p["loop"] or p["source"] in LIVE or first_ns is None or last_ns is None:
                return
            offset += last_ns - first_ns + period

    def _opener(self) -> Callable[[], Iterator[list[Message]]]:
        """Check the source's input now (clear errors at open); return a pass factory."""
        p = self.params
        src = p["source"]
        if src == "session":
            return self._session_pass()
        if src == "mcap":
            return self._mcap_pass()
        if src == "sim":
            return self._sim_pass()
        return self._live_pass()

    # ----------------------------------------------------------------- session

    def _session_pass(self) -> Callable[[], Iterator[list[Message]]]:
        p = self.params
        if not p["path"]:
            raise InputError("grab", "source=session needs path=<session folder>")
        reader = SessionReader(p["path"])
        self.camera_doc = dict(reader.camera_doc)
        present = reader.recordings()
        wanted = _selected(p["recordings"])
        if wanted:
            missing = [w for w in wanted if w not in present]
            if missing:
                raise InputError(
                    reader.root, f"no recording folder {missing[0]}/ (present: {present})"
                )
            # Protocol order whatever the order asked: walks need the static model first.
            names = recording_order(wanted)
        else:
            # The whole protocol: later stages wait for the scene calibration and the
            # static model, so a session without them cannot be analysed.
            miss = reader.missing(PROTOCOL)
            if miss:
                raise InputError(
                    reader.root,
                    f"missing recording folder {miss[0]}/ (a session needs calibration/ and "
                    "static/ before the walks; set recordings= to play only some)",
                )
            names = present
        for name in names:
            # Parse every frames.csv now: a bad one is refused before any frame goes out.
            reader.rows(name)
        camera = p["camera"]

        def one_pass() -> Iterator[list[Message]]:
            for name in names:
                seen = len(reader.warnings)
                before = dict(reader.skipped)
                for raw in iter_raw_frames(reader, name, camera):
                    self._sync_reader(reader, before, seen)
                    before, seen = dict(reader.skipped), len(reader.warnings)
                    yield [raw]
                self._sync_reader(reader, before, seen)

        return one_pass

    def _sync_reader(self, reader: SessionReader, before: dict[str, int], seen: int) -> None:
        for reason, n in reader.skipped.items():
            self.counters[reason] = self.counters.get(reason, 0) + n - before.get(reason, 0)
        for line in reader.warnings[seen:]:
            if len(self.warnings) < 200:
                self.warnings.append(line)
            log.warning("grab: %s", line)

    # ----------------------------------------------------------------- mcap

    def _mcap_pass(self) -> Callable[[], Iterator[list[Message]]]:
        from gaitflow.recording import iter_messages  # the recorder's module, lazily

        p = self.params
        path = Path(p["path"]) if p["path"] else None
        if path is None:
            raise InputError("grab", "source=mcap needs path=<recording.mcap>")
        if not path.is_file():
            raise InputError(path, "recording not found")
        wanted = set(_selected(p["recordings"]))
        camera = p["camera"]

        def decoded() -> Iterator[Message]:
            for key, payload, _log_ns, _pub_ns in iter_messages(path, streams=("raw", "truth")):
                try:
                    schema = peek_header(payload).get("schema")
                    cls = {"raw": RawFrame, "truth": GroundTruth}.get(str(schema))
                    if cls is None:
                        continue
                    msg = decode(cls, payload)
                except SchemaError as exc:
                    self._count("bad_payload", f"{path}: message on {key}: {exc}")
                    continue
                if wanted and msg.header.trial not in wanted:
                    continue
                yield _restamp(msg, camera=camera)

        def one_pass() -> Iterator[list[Message]]:
            # Group each raw frame with the truth of the same frame, whichever came first.
            group: list[Message] = []
            for msg in decoded():
                h = msg.header
                if group and (h.trial, h.frame) != (group[0].header.trial, group[0].header.frame):
                    if any(isinstance(m, RawFrame) for m in group):
                        yield _raw_first(group)
                    group = []
                group.append(msg)
            if any(isinstance(m, RawFrame) for m in group):
                yield _raw_first(group)

        return one_pass

    # ----------------------------------------------------------------- sim

    def _sim_pass(self) -> Callable[[], Iterator[list[Message]]]:
        from gaitflow.sim import list_trials  # the simulator is heavy: import lazily
        from gaitflow.sim.config import SimConfig
        from gaitflow.sim.session import simulate_session

        p = self.params
        trials = list_trials()
        trial = p["trial"] or trials[0]
        if trial not in trials:
            raise InputError("grab", f"trial={trial!r} is not a bundled trial; known: {trials}")
        config = SimConfig.quick() if p["quick"] else SimConfig()
        # Building the session renders nothing yet; it gives the recordings and camera.json.
        sim = simulate_session(trial, p["seed"], config)
        self.camera_doc = dict(sim.camera_json)
        names = recording_order(sim.recordings)
        wanted = _selected(p["recordings"])
        if wanted:
            missing = [w for w in wanted if w not in names]
            if missing:
                raise InputError("grab", f"the simulator has no recording {missing[0]!r}")
            names = [n for n in names if n in wanted]
        camera = p["camera"]

        def one_pass() -> Iterator[list[Message]]:
            for name in names:
                for raw, truth in sim.recordings[name]:
                    yield [_restamp(raw, camera=camera), _restamp(truth, camera=camera)]

        return one_pass

    # ----------------------------------------------------------------- live

    def _live_pass(self) -> Callable[[], Iterator[list[Message]]]:
        from gaitflow.drivers import make_driver

        p = self.params
        names = _selected(p["recordings"]) or ["walk-01"]
        if len(names) != 1:
            raise InputError("grab", f"a live source records one trial at a time, got {names}")
        trial, camera = names[0], p["camera"]

        # Open the camera now: a missing driver package or device fails at open.
        driver = make_driver(p["source"])
        driver.open()
        self.camera_doc = driver.intrinsics()
        self._driver = driver

        def one_pass() -> Iterator[list[Message]]:
            try:
                for i, (ts, ir, depth) in enumerate(driver.frames()):
                    hdr = RawFrame.make_header(camera, trial, i, ts)
                    # the device's camera.json travels with its frames (calibrate adopts it)
                    yield [RawFrame(header=hdr, ir=ir, depth=depth, camera=self.camera_doc or {})]
            finally:
                driver.close()

        return one_pass


def _raw_first(group: list[Message]) -> list[Message]:
    return sorted(group, key=lambda m: not isinstance(m, RawFrame))


def _mark_last(groups: Iterable[list[Message]]) -> Iterator[list[Message]]:
    """Set ``last=True`` on the final frame of each trial (one frame of look-ahead).

    A frame is last when the next frame belongs to another trial or there is none. Sources
    that already flag it pass through unchanged; a recording cut short gets its flag, so
    downstream stages still close the trial.
    """
    held: list[Message] | None = None
    for group in groups:
        if held is not None:
            is_last = group[0].header.trial != held[0].header.trial
            yield [_restamp(m, last=is_last) for m in held]
            held = None
        if group[0].header.last:
            yield group  # already flagged by the source: no need to wait for the next one
        else:
            held = group
    if held is not None:
        yield [_restamp(m, last=True) for m in held]


def open_source(params: dict[str, Any]) -> GrabSource:
    """Open the source described by resolved ``params`` (``SPEC.params.resolve(...)``)."""
    return GrabSource(params)


SPEC = SourceSpec(
    name="grab",
    params=PARAMS,
    open=open_source,
    doc=__doc__ or "",
)
