"""``armid serve``: the estimator service. Streamed experiments in, the arm's parameters out.

It subscribes to ``armid/<robot>/joint_state`` and ``armid/<robot>/events``, cuts each
experiment out of the stream by the sequence numbers its ``stop`` event gives
(:mod:`daq.experiment_stream`), holds its records in memory
(:class:`~armid.schema.joint_states.JointStates`), and then, reading them there (the same
numbers as reading its copy: :func:`~armid.identify.recordings.recording_of` either way):

- a **single-link** experiment (one joint moved): Khosla's off-line sequence over every
  single-link experiment received so far, last link first, each link with the later links
  known (:func:`identify.single_link.single_link_sequence`), on the excitation window of
  each run as ``armid demo`` cuts it;
- a **whole-arm** run: ``armid identify`` on that run (the same reader, preparation and
  options: the estimate equals ``armid identify`` on the recording), validated on the other
  whole-arm runs received; every earlier whole-arm fit is validated again on the new run.

After each experiment it publishes ``armid/<robot>/estimate/parameters`` (JSON, below). Once
a whole-arm fit exists it also runs the on-line payload estimator on the live stream
(:class:`daq.payload_service.PayloadService`, beside it in the same session:
``armid/<robot>/estimate/payload`` as ``armid estimate live`` publishes it).

Each experiment's records are written afterwards, for the archive, to ``<out>/<run>/run.mcap``
(by the recorder ``armid record`` uses).

Threads, so that nothing waits on the arithmetic: Zenoh's callbacks only queue bytes; an
ingest thread files records by sequence number; an analysis thread identifies. The ingest
never holds up the stream: when it falls more than ``max_backlog`` records behind it skips to
the newest and counts what it skipped, and an experiment is then identified on the records
it kept (``experiment.kept`` gives their sequence ranges, ``experiment.missing`` how many of
the recording's it lacks). Acquisition and recording happen in the process that streams, on
their own unbounded queue: a slow service costs them nothing.

``estimate/parameters`` document::

    {"robot", "time", "experiment": {"run", "kind", "link", "records", "missing", "skipped", "kept", "completed", "mcap"},
     "links_done": [6, 5, ...], "single_link": {"order", "steps", "table": [{"link", "parameter", "estimate", "std", ...}]},
     "whole_arm": {"<run>": {"base_parameters": [{"expression", "value", "std"}], "fit", "validation", "validated_on", ...}},
     "base_parameters": [...], "validation": {...} | null, "source": "whole_arm <run>" | "single_link"}

``base_parameters`` are the newest whole-arm run's once there is one, else the single-link
table's (expression, value, std, link).
"""

from __future__ import annotations

import json
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from armid.daq.experiment_stream import CollectedExperiment, ExperimentCollector, event_of
from armid.daq.stream import key
from armid.identify.plausibility import MOVING_RAD, moving_joints
from armid.identify.robot import Robot
from armid.schema.joint_state import check_encoding
from armid.schema.joint_states import JointStates

from .pipeline import RECIPES

WHOLE_ARM_PIPELINES = tuple(RECIPES)
"""How a whole-arm run is identified, by the name of its recipe in :data:`armid.pipeline.RECIPES`:
``identify`` as ``armid identify RUN.mcap`` does (:data:`~armid.pipeline.USER_LOG`: the whole
recording, low-pass chosen from the data, weighted least squares); ``drives`` as ``armid demo``
does (:data:`~armid.pipeline.DRIVE_RUN`: the excitation window, the drives' velocity, no
low-pass, reversals left out)."""


@dataclass(frozen=True)
class ServiceOptions:
    max_backlog: int = 2500
    """Records queued in the ingest before it skips to the newest (5 s at 2 ms)."""
    whole_arm: str = "identify"
    payload: bool = True
    """Run the payload estimator on the live stream once a whole-arm fit exists."""
    experiments: int | None = None
    """File this many experiments and no more (None: every one): a run that starts after them is
    not the service's (a session's payload run, which a payload estimator follows)."""
    stop_wait_s: float = 5.0
    ingest_delay_s: float = 0.0
    """Seconds of extra work per record in the ingest: a slow consumer by design (tests)."""


class EstimatorService:
    """Run the estimator service on an open Zenoh session until :meth:`close`."""

    def __init__(self, session: Any, robot: Robot, out: Path, options: ServiceOptions | None = None,
                 on_publish: Callable[[dict[str, Any]], None] | None = None, log: Callable[[str], None] | None = None) -> None:
        import zenoh

        self.session = session
        self.robot = robot
        self.name = robot.name
        self.out = Path(out)
        self.options = options or ServiceOptions()
        if self.options.whole_arm not in WHOLE_ARM_PIPELINES:
            raise ValueError(f"whole_arm must be one of {', '.join(WHOLE_ARM_PIPELINES)}, got {self.options.whole_arm!r}")
        self.on_publish = on_publish
        self.log = log or (lambda _m: None)
        self.collector = ExperimentCollector(stop_wait_s=self.options.stop_wait_s)
        self._inbox: deque[bytes] = deque()
        self._events: deque[dict[str, Any]] = deque()
        self._jobs: deque[CollectedExperiment] = deque()
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._job_ready = threading.Event()
        self.received = 0
        self.skipped = 0
        self.lost = 0
        self.bad = 0
        self.last_bad: str | None = None
        self._last_seq: int | None = None
        self.published = 0
        self.errors: list[str] = []
        self.drive_reports: dict[tuple[Any, ...], dict[str, Any]] = {}  # what the drives said, by kind, joint and code
        self.experiments: list[dict[str, Any]] = []
        self.last: dict[str, Any] | None = None
        self.busy: str | None = None
        # what the analysis has so far
        self._single: dict[int, Any] = {}  # 0-based link -> Prepared
        self._single_runs: dict[int, str] = {}
        self._sequence_doc: dict[str, Any] | None = None
        self.sequence: Any = None
        self._whole: dict[str, Any] = {}  # run -> Prepared
        self.whole_fits: dict[str, Any] = {}  # run -> IdentificationResult
        self._whole_docs: dict[str, dict[str, Any]] = {}
        self._names: set[str] = set()  # every experiment's name so far (_with_identity)
        self._filed: set[str] = set()  # the runs whose start was filed (options.experiments)
        self.not_filed: list[str] = []  # the runs that started after them
        self.payload_service: Any = None
        self._pub = session.declare_publisher(key(self.name, "estimate/parameters"), encoding=zenoh.Encoding.APPLICATION_JSON,
                                              congestion_control=zenoh.CongestionControl.BLOCK)  # a fit, once an experiment: never dropped
        self._token = session.liveliness().declare_token(key(self.name, "alive/estimator"))
        self._queryable = session.declare_queryable(key(self.name, "status"), self._on_query)
        self._subs = [session.declare_subscriber(key(self.name, "joint_state"), self._on_record),
                      session.declare_subscriber(key(self.name, "events"), self._on_event)]
        self._threads = [threading.Thread(target=self._ingest, name="armid-serve-ingest", daemon=True),
                         threading.Thread(target=self._analyse, name="armid-serve-analysis", daemon=True)]
        for t in self._threads:
            t.start()

    # -- Zenoh callbacks: queue only (a callback never kills the receive thread) --------------
    def _on_record(self, sample: Any) -> None:
        try:
            check_encoding(str(sample.encoding))
            self._inbox.append(sample.payload.to_bytes())
            self._wake.set()
        except Exception as err:
            self._bad(err)

    def _bad(self, err: BaseException) -> None:
        """A put that is not a record this service reads (another encoding, malformed bytes):
        counted, the first said."""
        self.bad += 1
        self.last_bad = f"{type(err).__name__}: {err}"
        self._error(err)
        if self.bad == 1:
            self.log(f"a put on joint_state refused ({self.last_bad}); further ones counted")

    def _on_event(self, sample: Any) -> None:
        try:
            doc = event_of(sample.payload.to_bytes())
            if doc is not None:
                self._events.append(doc)
                self._wake.set()
        except Exception as err:
            self._error(err)

    def _error(self, err: BaseException) -> None:
        if len(self.errors) < 100:
            self.errors.append(f"{type(err).__name__}: {err}")

    # -- ingest ------------------------------------------------------------------------------------
    def _ingest(self) -> None:
        delay = self.options.ingest_delay_s
        while not self._stop.is_set():
            self._wake.wait(0.1)
            self._wake.clear()
            try:
                while self._events:
                    self._take_event(self._events.popleft())
                while self._inbox and not self._stop.is_set():
                    backlog = len(self._inbox)
                    if backlog > self.options.max_backlog:
                        for _ in range(backlog - 1):  # behind: skip to the newest record
                            self._inbox.popleft()
                        self.skipped += backlog - 1
                        self._last_seq = None
                    data = self._inbox.popleft()
                    try:
                        states = JointStates.unpack(data)
                    except ValueError as err:
                        self._bad(err)
                        continue
                    first = int(states.sequence[0])
                    if self._last_seq is not None and first > self._last_seq + 1:
                        self.lost += first - self._last_seq - 1
                    self._last_seq = int(states.sequence[-1])
                    self.received += len(states)
                    self.collector.record(states)
                    if delay:
                        time.sleep(delay)
                    while self._events:
                        self._take_event(self._events.popleft())
                    if self.collector.stopping:
                        self._queue_completed()
                self._queue_completed()
            except Exception as err:
                self._error(err)

    def _take_event(self, doc: dict[str, Any]) -> None:
        """An experiment's start or stop to the collector; a drive's fault or event (the
        recorder's :class:`~armid.daq.supervision.Supervision`) said once per kind, joint
        and code, and counted in the status."""
        if doc.get("event") not in ("fault", "drive_event"):
            if self._beyond_the_experiments(doc):
                return
            self.collector.event(doc)
            return
        key = (doc.get("event"), doc.get("type"), doc.get("joint"), doc.get("code"))
        seen = self.drive_reports.get(key)
        if seen is not None:
            seen["count"] += 1
            return
        text = doc.get("meaning") or doc.get("message") or "?"
        where = f"joint {doc.get('joint')}" + (f" (node {doc['node']})" if doc.get("node") is not None else "")
        self.drive_reports[key] = {"event": doc.get("event"), "type": doc.get("type"), "joint": doc.get("joint"), "code": doc.get("code"),
                                   "text": text, "count": 1}
        self.log(f"the drives said: {where}: {text}" if doc.get("event") == "fault" else f"the drives said: {text}")

    def _beyond_the_experiments(self, doc: dict[str, Any]) -> bool:
        """Whether ``doc`` (a run's start or stop) belongs to a run after the ``experiments`` the
        service files: not filed, said once per run."""
        limit, run = self.options.experiments, doc.get("run")
        if limit is None or not isinstance(run, str) or run in self._filed:
            return False
        if doc.get("event") == "start" and len(self._filed) < limit:
            self._filed.add(run)
            return False
        if run not in self.not_filed:
            self.not_filed.append(run)
            self.log(f"{run}: not filed: the service files {limit} experiment{'s' if limit != 1 else ''} ({', '.join(sorted(self._filed))})")
        return True

    @property
    def done(self) -> bool:
        """Every one of the ``experiments`` it files is identified (or said not to be) and published."""
        limit = self.options.experiments
        return limit is not None and len(self.experiments) >= limit and self.idle

    def _queue_completed(self) -> None:
        for exp in self.collector.completed():
            self._jobs.append(exp)
            self._job_ready.set()

    # -- analysis ----------------------------------------------------------------------------------
    def _analyse(self) -> None:
        while not self._stop.is_set():
            self._job_ready.wait(0.1)
            self._job_ready.clear()
            while self._jobs and not self._stop.is_set():
                exp = self._jobs.popleft()
                self.busy = exp.name
                try:
                    doc = self.process(exp)
                    if doc is not None:
                        self.publish(doc)
                except Exception as err:
                    self._error(err)
                    self.log(f"{exp.name}: not identified: {type(err).__name__}: {err}")
                    info = {**self._info(exp), "error": f"{type(err).__name__}: {err}", "note": f"not identified: {type(err).__name__}: {err}"}
                    self.experiments.append(info)
                    self._say_failed(info)
                finally:
                    self.busy = None

    def _say_failed(self, info: dict[str, Any]) -> None:
        """An experiment the analysis failed on, published as any other (the estimates so
        far, the reason in its note): a subscriber that waits for the run hears of it."""
        try:
            self.publish(self._document(info))
        except Exception as err:
            self._error(err)

    @property
    def still_running(self) -> list[str]:
        """After :meth:`close`: what outlived its wait (an identification in the middle of a long
        step), by thread name; such a thread must not meet the interpreter's exit (a thread inside
        compiled code there aborts the process)."""
        names = [t.name for t in self._threads if t.is_alive()]
        return names + (["armid-payload"] if self.payload_service is not None and self.payload_service.running else [])

    @property
    def idle(self) -> bool:
        """Nothing received waits to be filed or identified."""
        return not (self._inbox or self._events or self._jobs or self.collector.stopping or self.busy)

    def held(self, exp: CollectedExperiment) -> tuple[JointStates, dict[str, Any]]:
        """The experiment's records as its recording holds them (stamped; shifted where ROS 2
        time cannot hold the stamps) and the recording's metadata."""
        desc = exp.description
        meta = dict(desc.get("metadata") or {})
        meta.setdefault("robot", self.name)
        meta["excitation"] = {k: v for k, v in desc.items() if k != "metadata"}
        meta["received_by"] = {"component": "estimator", "missing": exp.missing, "kept": exp.kept}
        records = exp.records
        stamped = np.isfinite(records.time)
        if not stamped.all():  # a record without a time has no place in a recording
            self.log(f"{exp.name}: left out {int((~stamped).sum())} record(s) whose time stamp is not finite")
            records = records[stamped]
        offset = _ros2_time_offset(records.time.tolist())
        if offset:
            meta["time_offset_s"] = offset
            self.log(f"{exp.name}: stamped beyond what ROS 2 time holds (after 2038-01-19): the copy's stamps are "
                     f"{offset:.0f} s earlier (time_offset_s in its metadata); the fit uses time differences only")
            records = replace(records, time=records.time - offset)
        return records, meta

    def write_copy(self, path: Path, records: JointStates, meta: dict[str, Any]) -> None:
        """The service's own recording of the experiment: what it received, as ``armid record`` writes it."""
        from armid.daq.recorder import McapRecorder

        rec = McapRecorder(path, [j.name for j in self.robot.joints], meta)
        try:
            rec.write(records)
        finally:
            rec.close()

    def recording(self, records: JointStates, meta: dict[str, Any], path: Path) -> Any:
        """The run as identification takes it, from memory: what reading its copy at ``path`` gives."""
        from armid.identify.recordings import recording_of
        from armid.io.recordings import run_period

        as_written = {k: v if isinstance(v, str) else json.dumps(v) for k, v in meta.items()}  # as the copy's metadata reads back
        return recording_of(records.recorded(), self.robot, str(path), [], run_period(as_written), None)

    def _with_identity(self, exp: CollectedExperiment) -> CollectedExperiment:
        """The experiment under a name no earlier one had: a run named as an earlier one
        (``armid excite --whole`` names every whole-arm run ``whole``) is told apart by the
        first sequence number of its records, so that it does not replace the first's copy
        and fit, and each whole-arm run is validated on the other."""
        if exp.name not in self._names:
            self._names.add(exp.name)
            return exp
        first = exp.sequences[0] if exp.sequences else exp.stop.get("first_sequence")
        unique, k = f"{exp.name}@{first}", 2
        while unique in self._names:
            unique, k = f"{exp.name}@{first}-{k}", k + 1
        self._names.add(unique)
        self.log(f"{exp.name}: a run of that name came before: this one is {unique}")
        return replace(exp, name=unique)

    def process(self, exp: CollectedExperiment) -> dict[str, Any] | None:
        """Identify on one collected experiment; the document to publish (None: nothing to say)."""
        exp = self._with_identity(exp)
        info = self._info(exp)
        if len(exp.records) < 50:
            info["note"] = f"only {len(exp.records)} records received: nothing identified"
            self.experiments.append(info)
            return self._document(info)
        records, meta = self.held(exp)
        path = self.out / _safe(exp.name) / "run.mcap"
        info["mcap"] = str(path)
        try:
            self._identify(exp, records, meta, path, info)
        finally:  # the archive's copy, after the analysis (which reads the records in memory)
            self.write_copy(path, records, meta)
        self.experiments.append(info)
        self.log(f"{exp.name}: {info.get('note') or 'identified'} ({len(exp.records)} records, {exp.missing} missing)")
        return self._document(info)

    def _identify(self, exp: CollectedExperiment, records: JointStates, meta: dict[str, Any], path: Path, info: dict[str, Any]) -> None:
        """The refusal, the kind and the identification, on the records in memory."""
        kind = exp.description.get("kind") or "recording"
        if not info["completed"]:
            info["note"] = f"the run was stopped ({exp.stop.get('reason')}): not identified"
            return
        link = exp.description.get("link")
        rec = self.recording(records, meta, path)
        for note in rec.notes:  # what identification left out, said as `armid identify` says it
            if note.startswith(("left out", "time goes backwards")):
                self.log(f"{exp.name}: {note}")
        if kind == "recording":
            kind, moving = self._kind_from_motion(rec)
            info["kind_from_motion"] = kind
            link = int(moving[0]) + 1 if kind == "single_link" else link
        refusal = self._refusal(kind, link, rec) if kind in ("single_link", "whole_arm") else None
        if refusal:
            info["note"] = refusal
        elif kind == "single_link" and isinstance(link, int):  # a link of the robot's (the refusal saw to it)
            self._single_link(exp, rec, path, link - 1, info)
        elif kind == "whole_arm":
            self._whole_arm(exp, rec, path, info)
        else:
            info["note"] = f"a {kind} experiment: neither single-link nor whole-arm, not identified"

    def _info(self, exp: CollectedExperiment) -> dict[str, Any]:
        """What a published document says of the experiment itself (INTERFACES.md)."""
        desc, stop = exp.description, exp.stop
        return {"run": exp.name, "kind": desc.get("kind") or "recording", "link": desc.get("link"), "records": len(exp.records),
                "missing": exp.missing, "kept": exp.kept, "completed": bool(stop.get("completed", True)),
                "reason": stop.get("reason"), "skipped_total": self.skipped, "timed_out": exp.timed_out}

    def _refusal(self, kind: str, link: Any, rec: Any) -> str | None:
        """Why a run cannot become the arm's parameters (None: it can): a claimed link that is
        not one of the robot's joints, or a run whose joints did not move (5.2: a trajectory
        that excites nothing determines nothing; identified, it published a condition number
        of 1.5e16 as the arm's parameters)."""
        n = self.robot.n_joints
        if kind == "single_link" and not (isinstance(link, int) and not isinstance(link, bool) and 1 <= link <= n):
            return f"the run claims link {link!r}, not a joint of {self.name} (1..{n}): not identified"
        moved = moving_joints(rec.q)
        still = [j + 1 for j in range(n) if not moved[j]]
        if kind == "single_link" and not moved[link - 1]:
            return f"not excited: link {link} did not move (range below {MOVING_RAD} rad): not identified"
        if kind == "whole_arm" and still:
            return f"not excited: joints {', '.join(map(str, still))} did not move (range below {MOVING_RAD} rad): not identified"
        return None

    def _kind_from_motion(self, rec: Any) -> tuple[str, np.ndarray[Any, np.dtype[np.intp]]]:
        """What a plain recording was, from which joints moved (and those joints)."""
        moving = np.flatnonzero(moving_joints(rec.q))
        if moving.size == self.robot.n_joints:
            return "whole_arm", moving
        return ("single_link" if moving.size == 1 else "partial"), moving

    def _single_link(self, exp: CollectedExperiment, rec: Any, path: Path, k: int, info: dict[str, Any]) -> None:
        from armid.identify.single_link import single_link_sequence

        from .pipeline import DRIVE_RUN

        stop = exp.stop
        self._single[k] = self._prepared(exp, rec, path, DRIVE_RUN)
        self._single_runs[k] = exp.name
        self.sequence = single_link_sequence(self.robot, {j: [p] for j, p in self._single.items()})
        doc = self.sequence.to_json()
        n = self.robot.n_joints
        done = sorted((j + 1 for j in self._single), reverse=True)
        for step in doc["steps"]:  # Khosla's order: a link is identified with every later link known
            step["later_links_known"] = all(j in self._single for j in range(step["link"], n))
            step["run"] = self._single_runs[step["link"] - 1]
        doc["links_done"] = done
        self._sequence_doc = doc
        info["window_s"] = stop.get("window_s")

    def _whole_arm(self, exp: CollectedExperiment, rec: Any, path: Path, info: dict[str, Any]) -> None:
        from . import pipeline

        recipe = pipeline.RECIPES[self.options.whole_arm]  # "identify": as `armid identify RUN.mcap`; "drives": as `armid demo`
        self._whole[exp.name] = self._prepared(exp, rec, path, recipe)
        for run in list(self._whole):  # each run's fit, validated on every other whole-arm run
            others = [p for r, p in self._whole.items() if r != run]
            fit, _ = pipeline.identify(self.robot, [self._whole[run]], others, recipe)  # poor excitation: the design's business
            self.whole_fits[run] = fit
            d = fit.to_json()
            d["validated_on"] = [r for r in self._whole if r != run]
            d["pipeline"] = self.options.whole_arm
            self._whole_docs[run] = d
        info["whole_arm_fit"] = exp.name
        if self.options.payload and self.payload_service is None:
            self._start_payload(self.whole_fits[exp.name])

    def _prepared(self, exp: CollectedExperiment, rec: Any, path: Path, recipe: Any) -> Any:
        """The run (from memory) through the pipeline by ``recipe``: a drive run cut to its
        excitation window (as ``armid demo`` cuts it), a user's log whole (as ``armid identify``
        reads it); what the checks found goes to the log."""
        from . import pipeline

        window = None
        if recipe.name == pipeline.DRIVE_RUN.name:
            period = float((exp.description.get("metadata") or {}).get("period_s") or 0.002)
            report = _report_of(exp, path)
            window = pipeline.Window(report.first_cycle, report.window_s, period)
        prep, found = pipeline.prepare_run(rec, self.robot, recipe, window)
        for warning in found:
            self.log(f"{exp.name}: warning: {warning}")
        return prep

    def _start_payload(self, fit: Any) -> None:
        from armid.daq.payload_service import EstimateStream, PayloadService
        from armid.identify.payload.rls import ArmModel, PayloadRLS

        arm = ArmModel(self.robot, tuple(fit.effects), fit.base.independent, fit.estimate.beta, fit.estimate.joint_sigma)
        estimator = PayloadRLS(arm)
        self.payload_service = PayloadService(self.session, self.name, EstimateStream(estimator), log=lambda line: self.log(f"payload: {line}"))
        self.log("payload estimator running on the live stream (estimate/payload)")

    def _document(self, info: dict[str, Any]) -> dict[str, Any]:
        newest_whole = next(reversed(self._whole_docs), None) if self._whole_docs else None
        doc: dict[str, Any] = {"robot": self.name, "time": time.time(), "experiment": info,
                               "links_done": sorted((j + 1 for j in self._single), reverse=True),
                               "single_link": self._sequence_doc, "whole_arm": self._whole_docs or None,
                               "received": self.received, "skipped": self.skipped, "lost": self.lost}
        if newest_whole is not None:
            w = self._whole_docs[newest_whole]
            doc["source"] = f"whole_arm {newest_whole}"
            doc["base_parameters"] = w["base_parameters"]
            doc["validation"] = w.get("validation")
        elif self._sequence_doc is not None:
            doc["source"] = "single_link"
            doc["base_parameters"] = [{"expression": r["parameter"], "value": r["estimate"], "std": r["std"], "link": r["link"]}
                                      for r in self._sequence_doc["table"]]
            doc["validation"] = None
        else:
            doc["source"], doc["base_parameters"], doc["validation"] = None, [], None
        return doc

    def publish(self, doc: dict[str, Any]) -> None:
        from .schema.json_text import strict_json

        text = strict_json(doc)
        # counted before the put: a subscriber that has the document must find it counted in `status`
        self.published += 1
        self.last = json.loads(text)
        self._pub.put(text)
        if self.on_publish is not None:
            self.on_publish(self.last)

    def _on_query(self, query: Any) -> None:
        from .schema.json_text import strict_json

        doc = {"component": "estimator", "received": self.received, "skipped": self.skipped, "lost": self.lost, "bad": self.bad,
               "backlog": len(self._inbox), "analysing": self.busy, "queued_experiments": len(self._jobs),
               "open_experiments": sorted(self.collector.started), "published": self.published,
               "experiments": self.experiments, "links_done": sorted((j + 1 for j in self._single), reverse=True),
               "whole_arm_runs": list(self._whole_docs), "errors": self.errors[-5:],
               "drive_reports": list(self.drive_reports.values())[-20:]}
        query.reply(key(self.name, "status"), strict_json(doc))

    def close(self) -> None:
        """Stop filing and identifying after the current step (all threads together up to
        :data:`~armid.daq.payload_service.STOP_WAIT_S`), then leave the session."""
        from armid.daq.payload_service import STOP_WAIT_S

        self._stop.set()
        self._wake.set()
        self._job_ready.set()
        if self.payload_service is not None:
            self.payload_service.request_stop()
        deadline = time.monotonic() + STOP_WAIT_S  # one wait for all: they stop side by side
        for t in self._threads:
            t.join(max(deadline - time.monotonic(), 0.0))
        if self.payload_service is not None:
            self.payload_service.close(max(deadline - time.monotonic(), 0.0))
        for entity in (*self._subs, self._queryable, self._token, self._pub):
            try:
                entity.undeclare()
            except Exception:  # already gone with the session
                pass


def _ros2_time_offset(stamps: list[float]) -> float:
    """Whole days to take off stamps that ROS 2's Time (int32 seconds) cannot hold, 0 when it can."""
    from armid.schema.joint_state import ROS2_SECONDS

    if not stamps or (ROS2_SECONDS[0] <= min(stamps) and max(stamps) < ROS2_SECONDS[1]):
        return 0.0
    return float(np.floor(min(stamps) / 86400.0) * 86400.0)


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name) or "run"


def _report_of(exp: CollectedExperiment, path: Path) -> Any:
    """The run's report as ``armid excite`` wrote it, from its ``stop`` event."""
    from armid.daq.excite import RunReport

    s = exp.stop
    w = s.get("window_s") or [0.0, float("inf")]
    return RunReport(exp.name, bool(s.get("completed", True)), s.get("reason"), s.get("stop_cycle"), int(s.get("cycles") or 0),
                     len(exp.records), int(s.get("first_cycle") or 0), [], [], [], str(path), (float(w[0]), float(w[1])))
