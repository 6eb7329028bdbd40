"""Rerun stream of a run: live to a viewer and/or saved to run.rrd, batched with send_columns.

Entity paths are the signal names (`/speed_est_mech_rad_s`); the timeline `t_s` is the drive clock.
`/flux_vector/true` and `/flux_vector/estimated` are 2D arrows derived from the flux magnitudes and
field angles, in per unit of the true flux magnitude (the true arrow has length 1 for either motor), for a
phasor view of how far the estimate is off in magnitude and angle.
`/events` holds trips and injections as text logs at their drive time, `/criteria/<n>` each criterion's result at
its window's start and end, and `/limits/<signal>/<n>/{low,high}` its limit band over its window where the limit is
in the signal's unit (shown in that signal's plot).
"""

from __future__ import annotations

import math
import os
import socket
import sys
import time
import urllib.parse
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np

RERUN_MODES = ("spawn", "connect", "save", "off")
APPLICATION_ID = "drivebench"
MAX_BATCH_ROWS = 20_000
# With only a file to write (no live viewer), batches of this much wall time: Rerun's FileSink keeps an index entry
# per chunk (one chunk per entity and batch) until the file is closed (its footer), so RSS grows with the number of
# batches: at 4 batches/s of 16 entities that was ~2.4 MB/min; at one batch per 5 s it is ~0.1 MB/min.
FILE_ONLY_INTERVAL_S = 5.0
LIVE_INTERVAL_S = 0.1
CLOSE_TIMEOUT_S = 10.0
FLUX_VECTOR_PERIOD_S = 0.01  # arrows are decimated to 100 Hz of drive time: a phasor view needs no more

PLOTS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("speed", ("speed_ref_mech_rad_s", "speed_est_mech_rad_s", "speed_true_mech_rad_s")),
    ("position error", ("pos_err_elec_rad",)),
    ("flux", ("flux_est_wb", "flux_true_wb")),
    ("currents", ("i_sx_a", "i_sy_a", "i_sx_ref_a", "i_sy_ref_a")),
    ("voltages", ("u_sx_v", "u_sy_v")),
    ("torque", ("torque_load_nm", "torque_est_nm")),
)


DEFAULT_VIEWER_URL = "rerun+http://127.0.0.1:9876/proxy"


def viewer_reachable(url: str, timeout_s: float = 1.0) -> bool:
    """Does something accept TCP connections at the URL's host:port? (the gRPC sink would retry silently)"""
    parsed = urllib.parse.urlsplit(url)
    host = parsed.hostname or "127.0.0.1"
    port = parsed.port or (443 if parsed.scheme.endswith("https") else 9876)
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            return True
    except OSError:
        return False


def viewer_executable() -> str | None:
    """The `rerun` viewer: on PATH, else next to this Python (a venv used without activating it)."""
    import shutil

    found = shutil.which("rerun")
    if found:
        return found
    beside = Path(sys.executable).parent / "rerun"
    return str(beside) if beside.exists() else None


def display_available() -> bool:
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


EVENT_COLOURS = {"trip": (214, 39, 40), "injection": (148, 103, 189)}
RGB = {"tab:green": (44, 160, 44), "tab:red": (214, 39, 40), "tab:orange": (255, 127, 14)}

FLUX_VECTOR_STYLE = {  # entity -> (colour, label)
    "flux_vector/true": ((170, 170, 170), "true"),
    "flux_vector/estimated": ((255, 140, 0), "estimated"),
}


def default_blueprint(recorded: Sequence[str] | None = None):
    """Time series of the recorded signals (all of PLOTS when not given) with their criteria's limit bands, the
    flux phasor view (only where flux and angles are recorded), and the events and verdicts as a text log."""
    import rerun.blueprint as rrb

    plots = []
    for title, names in PLOTS:
        shown = [name for name in names if recorded is None or name in recorded]
        if shown:
            contents = [f"/{name}" for name in shown] + [f"/limits/{name}/**" for name in shown]
            plots.append(rrb.TimeSeriesView(name=title, origin="/", contents=contents))
    views = list(plots)
    if recorded is None or {"flux_est_wb", "flux_true_wb", "pos_est_elec_rad", "pos_err_elec_rad"} <= set(recorded):
        views.append(rrb.Spatial2DView(name="flux vector, p.u. of true flux (grey true, orange estimated)",
                                       origin="/flux_vector",
                                       visual_bounds=rrb.VisualBounds2D(x_range=[-1.3, 1.3], y_range=[-1.3, 1.3])))
    views.append(rrb.TextLogView(name="trips, injections, criteria", origin="/",
                                 contents=["/events/**", "/criteria/**"]))
    # following: a viewer that opens a run while it goes shows its newest data (the service's live view)
    return rrb.Blueprint(rrb.Grid(*views), rrb.TimePanel(timeline="t_s", play_state="following"),
                         collapse_panels=True)


def _env_seconds(name: str, default: float, warn: Callable[[str], None]) -> float:
    text = os.environ.get(name)
    if not text:
        return default
    try:
        value = float(text)
        if math.isfinite(value) and 0.0 <= value <= 3600.0:
            return value
    except ValueError:
        pass
    warn(f"rerun: {name}={text!r} is not seconds in [0, 3600]; using {default:g} s")
    return default


def _warn(message: str) -> None:
    print(message, file=sys.stderr)


class RerunStream:
    """Buffers samples and sends them in batches of at least `batch_s` of drive time and at most about
    one batch per `min_wall_interval_s` of wall time."""

    def __init__(
        self,
        mode: str,
        rrd_path: Path | None,
        *,
        url: str | None = None,
        recording_name: str = "run",
        recorded: Sequence[str] | None = None,
        batch_s: float = 0.1,
        min_wall_interval_s: float | None = None,
        warn: Callable[[str], None] = _warn,
    ):
        if mode not in RERUN_MODES:
            raise ValueError(f"rerun mode must be one of {', '.join(RERUN_MODES)}, not {mode!r}")
        self.mode = mode
        self.batch_s = batch_s
        self.min_wall_interval_s = LIVE_INTERVAL_S if min_wall_interval_s is None else min_wall_interval_s
        self.rrd_path = rrd_path
        self._rec = None
        self._warn = warn
        self._times: list[float] = []
        self._rows: list[Mapping[str, float]] = []
        self._blocks: list[tuple[np.ndarray, dict[str, np.ndarray]]] = []   # log_columns() blocks not yet sent
        self._block_rows = 0
        self._last_send = time.monotonic()
        self._last_arrow_bin = -math.inf
        self.sinks: list[str] = []   # what the stream really goes to: "file", "viewer"
        self._styled: set[str] = set()
        self._recorded = tuple(recorded) if recorded is not None else None
        if mode == "off":
            return

        import rerun as rr

        self._rr = rr
        # a run started by `drivebench serve` is recording `run-ID`, named as its pages name it (`run-ID · scenario`)
        recording_id = os.environ.get("DRIVEBENCH_RECORDING_ID") or recording_name
        recording_name = os.environ.get("DRIVEBENCH_RECORDING_NAME") or recording_name
        self._rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id)
        sinks: list = []
        if rrd_path is not None:
            sinks.append(rr.FileSink(str(rrd_path)))
            self.sinks.append("file")
        if mode == "spawn":
            if not display_available():
                warn("rerun: no display (DISPLAY/WAYLAND_DISPLAY unset); not spawning a viewer, saving run.rrd only")
            else:
                try:
                    rr.spawn(connect=False, detach_process=True, executable_path=viewer_executable(),
                             recording=self._rec)
                    if not viewer_reachable(DEFAULT_VIEWER_URL):
                        raise RuntimeError("the viewer did not start (no X/Wayland connection?)")
                    sinks.append(rr.GrpcSink(DEFAULT_VIEWER_URL))
                    self.sinks.append("viewer")
                except Exception as exc:  # the viewer binary or its window may be missing
                    warn(f"rerun: could not spawn the viewer ({exc}); saving run.rrd only")
        elif mode == "connect":
            url = url or DEFAULT_VIEWER_URL
            if viewer_reachable(url):
                sinks.append(rr.GrpcSink(url))
                self.sinks.append("viewer")
            else:
                warn(f"rerun: no viewer answers at {url}; saving run.rrd only")
        if not sinks:
            self._rec = None
            return
        if self.sinks == ["file"] and min_wall_interval_s is None:
            # the service's live view follows run.rrd: `serve --live` asks for a shorter interval
            self.min_wall_interval_s = _env_seconds("DRIVEBENCH_RERUN_INTERVAL_S", FILE_ONLY_INTERVAL_S, warn)
        self._rec.set_sinks(*sinks, default_blueprint=default_blueprint(recorded))
        self._rec.send_recording_name(recording_name)
        self._style()

    @property
    def enabled(self) -> bool:
        return self._rec is not None

    def _style(self) -> None:
        """Series names for the signals this run records (no entity declared that nothing fills); the phasor's
        arrows coloured, unlabelled (two labels at one origin overlap: the view's title names the colours)."""
        rr = self._rr
        for _, names in PLOTS:
            for name in names:
                if self._recorded is None or name in self._recorded:
                    self._rec.log(name, rr.SeriesLines(names=name), static=True)
        if self._recorded is None or "flux_est_wb" in self._recorded:
            for entity, (colour, _label) in FLUX_VECTOR_STYLE.items():
                self._rec.log(entity, rr.Arrows2D.from_fields(colors=[colour], show_labels=False), static=True)

    def log_event(self, t_s: float, kind: str, text: str) -> None:
        """A trip ("trip") or an injection ("injection") at its drive time."""
        if self._rec is None or not math.isfinite(t_s):
            return
        try:
            rr = self._rr
            self._rec.set_time("t_s", duration=float(t_s))
            self._rec.log(f"events/{kind}", rr.TextLog(text, level="ERROR" if kind == "trip" else "INFO",
                                                       color=EVENT_COLOURS.get(kind)))
        except Exception as exc:
            self._warn(f"rerun: logging stopped ({type(exc).__name__}: {exc}); run.rrd may be incomplete")
            self._drop()

    def log_judgement(self, criteria: Sequence[Mapping], params: Mapping[str, Mapping] | None = None) -> None:
        """Each criterion's result at its window's start and end, and its limit band on its signal's plot."""
        if self._rec is None:
            return
        from bench.outputs.summary_plot import COLOURS, _band, _status

        try:
            rr = self._rr
            for n, c in enumerate(criteria):
                window = c.get("window_s") or ()
                if len(window) != 2:
                    continue
                status = _status(c)
                colour = RGB.get(COLOURS[status], (200, 200, 200))
                unit = f" {c.get('unit')}" if c.get("unit") else ""
                text = (f"{c.get('name')}: {status.replace('_', ' ')}, value {c.get('value')} / limit "
                        f"{c.get('limit')}{unit} ({c.get('kind')} of {c.get('signal')})")
                level = {"pass": "INFO", "fail": "ERROR"}.get(status, "WARN")
                for t, what in ((float(window[0]), "window opens"), (float(window[1]), "window closes")):
                    self._rec.set_time("t_s", duration=t)
                    self._rec.log(f"criteria/{n}", rr.TextLog(f"{what}: {text}", level=level, color=colour))
                band = _band(c, (params or {}).get(str(c.get("name"))) or {})
                if band is None:
                    continue
                for edge, value in zip(("low", "high"), band):
                    entity = f"limits/{c.get('signal')}/{n}/{edge}"
                    self._rec.log(entity, rr.SeriesLines(names=f"limit: {c.get('name')}", colors=[colour]),
                                  static=True)
                    self._rec.send_columns(entity, indexes=[rr.TimeColumn("t_s", duration=[*map(float, window)])],
                                           columns=rr.Scalars.columns(scalars=[value, value]))
        except Exception as exc:
            self._warn(f"rerun: logging stopped ({type(exc).__name__}: {exc}); run.rrd may be incomplete")
            self._drop()

    def log_rows(self, t_s: Sequence[float], values: Sequence[Mapping[str, float]]) -> None:
        """Append samples (one mapping of signal -> value per time) and send once a batch is full."""
        if self._rec is None:
            return
        self._times.extend(t_s)
        self._rows.extend(values)
        if not self._times or self._times[-1] - self._times[0] < self.batch_s:
            return
        # at most ~10 batches per wall second: a lockstep run faster than real time sends bigger batches
        if time.monotonic() - self._last_send >= self.min_wall_interval_s or len(self._times) >= MAX_BATCH_ROWS:
            self._flush_rows()

    def log_columns(self, t_s: np.ndarray, columns: Mapping[str, np.ndarray]) -> None:
        """A block of columns: sent with the blocks before it once `min_wall_interval_s` has passed (or the rows
        reach MAX_BATCH_ROWS)."""
        if self._rec is None or len(t_s) == 0:
            return
        self._flush_rows()
        self._blocks.append((np.array(t_s, dtype=np.float64),
                             {k: np.array(v, dtype=np.float64) for k, v in columns.items()}))
        self._block_rows += len(t_s)
        if time.monotonic() - self._last_send >= self.min_wall_interval_s or self._block_rows >= MAX_BATCH_ROWS:
            self._flush_blocks()

    def flush(self) -> None:
        self._flush_rows()
        self._flush_blocks()

    def _flush_blocks(self) -> None:
        if self._rec is None or not self._blocks:
            return
        blocks, self._blocks, self._block_rows = self._blocks, [], 0
        names = dict.fromkeys(name for _, columns in blocks for name in columns)
        t = np.concatenate([b[0] for b in blocks])
        columns = {n: np.concatenate([c[n] if n in c else np.full(len(bt), np.nan) for bt, c in blocks])
                   for n in names}
        self._last_send = time.monotonic()
        self._send(t, columns)

    def _flush_rows(self) -> None:
        if self._rec is None or not self._times:
            return
        t = np.asarray(self._times, dtype=np.float64)
        rows = self._rows
        names = dict.fromkeys(name for row in (rows[0], rows[-1]) for name in row)
        columns = {
            name: np.fromiter((row.get(name, math.nan) for row in rows), dtype=np.float64, count=len(rows))
            for name in names
        }
        self._times = []
        self._rows = []
        self._last_send = time.monotonic()
        self._send(t, columns)

    def _send(self, t: np.ndarray, columns: Mapping[str, np.ndarray]) -> None:
        try:
            rr = self._rr
            index = [rr.TimeColumn("t_s", duration=t)]
            for name, values in columns.items():
                self._rec.send_columns(name, indexes=index, columns=rr.Scalars.columns(scalars=values))
            self._send_flux_vectors(t, columns)
        except Exception as exc:  # the view must never break a run: stop logging, keep the run going
            self._warn(f"rerun: logging stopped ({type(exc).__name__}: {exc}); run.rrd may be incomplete")
            self._drop()

    def _send_flux_vectors(self, t: np.ndarray, columns: Mapping[str, np.ndarray]) -> None:
        needed = ("flux_est_wb", "flux_true_wb", "pos_est_elec_rad", "pos_err_elec_rad")
        if not all(name in columns for name in needed):
            return
        bins = np.floor(t / FLUX_VECTOR_PERIOD_S)
        first = np.ones(len(t), dtype=bool)
        first[1:] = bins[1:] != bins[:-1]
        idx = np.flatnonzero(first & (bins > self._last_arrow_bin))
        if len(idx) == 0:
            return
        self._last_arrow_bin = bins[idx[-1]]
        angle_est = columns["pos_est_elec_rad"][idx]
        angle_true = angle_est + columns["pos_err_elec_rad"][idx]
        base = np.abs(columns["flux_true_wb"][idx])
        base[~(base > 0)] = np.nan
        rr = self._rr
        index = [rr.TimeColumn("t_s", duration=t[idx])]
        for entity, magnitude, angle in (
            ("flux_vector/estimated", columns["flux_est_wb"][idx] / base, angle_est),
            ("flux_vector/true", columns["flux_true_wb"][idx] / base, angle_true),
        ):
            vectors = np.stack([magnitude * np.cos(angle), magnitude * np.sin(angle)], axis=1)
            vectors = np.nan_to_num(vectors)
            self._rec.send_columns(
                entity, indexes=index, columns=rr.Arrows2D.columns(vectors=vectors, origins=np.zeros_like(vectors))
            )

    def close(self) -> None:
        if self._rec is None:
            return
        try:
            self.flush()
            if self._rec is not None:
                self._rec.flush(timeout_sec=CLOSE_TIMEOUT_S)
        except Exception as exc:
            self._warn(f"rerun: could not deliver everything ({type(exc).__name__}: {exc})")
        finally:
            self._drop()

    def _drop(self) -> None:
        rec, self._rec = self._rec, None
        if rec is not None:
            try:
                rec.disconnect()  # writes the .rrd footer
            except Exception as exc:
                self._warn(f"rerun: closing the stream failed ({type(exc).__name__}: {exc})")


def rrd_entity_paths(path: Path) -> set[str]:
    """Entity paths present in a saved .rrd (for checks and tests)."""
    from rerun.chunk import RrdReader

    store = RrdReader(path).store()
    paths = set()
    for line in store.summary().splitlines():
        entity = line.split(" ", 1)[0]
        if entity.startswith("/"):
            paths.add(entity)
    return paths


def rrd_recording(path: Path) -> tuple[str, str | None]:
    """(recording id, recording name) of the recording in a saved .rrd (for checks and tests)."""
    from rerun.chunk import RrdReader

    reader = RrdReader(path)
    ids = [entry.recording_id for entry in reader.recordings()]
    if len(ids) != 1:
        raise ValueError(f"{path}: {len(ids)} recordings, expected one")
    name = None
    for chunk in reader.store().stream():
        if chunk.entity_path == "/__properties":
            names = chunk.to_record_batch().to_pydict().get("RecordingInfo:name")
            if names:
                name = names[-1][0]
    return ids[0], name
