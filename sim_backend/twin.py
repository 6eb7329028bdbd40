"""The rig's twin: replay a recorded run through the simulated drive and show where the two part.

A run directory (record.json + telemetry.parquet, the documented layout of docs/records.md) is read with json and
pyarrow directly: sim_backend does not import bench. The replay drives the drive model itself (plant, inverter and
firmware kernels; no protocol server, no lockstep bench loop) with what the rig's drive and instruments recorded:

- the speed reference as the drive received it (`speed_ref_mech_rad_s`, the drive's own ramped reference),
- the load as the reference sensor measured it (`torque_load_nm`, replayed as an active torque),
- the injections at the times the record says (`injections_applied`; else the scenario file's [[injection]]s, read
  with tomllib when its sha256 is the one in the record).

On an instruments rig (the run's bench config has [simulator.instruments]: `Instruments`) the replayed load is the
transducer's reading minus the dyno rotor's J_dyno dw/dt, and the twin's shaft speed is shown through the encoder's
gate at its reading instants (docs/twin.md, "On the instruments rigs").

Time: a recorded row stamped t_s = n T (T the control period) is the firmware's output of its n-th period; the replay
steps the model to the same period and takes that row. Each chunk between two recorded rows runs with the reference
and the load of the chunk's last row (the load machine's setpoint changes on a SYNC, and the first row that shows a
change is the one at the end of the chunk it happened in; the drive's ramp limiter catches a reference that moved).

The tube: sim_backend/twin_tube.py.
"""

from __future__ import annotations

import hashlib
import json
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from scipy.signal import lfilter

from drivers.contract.signals import SIGNAL_NAMES, TIME_COLUMN
from drivers.contract.errors import InputError
from sim_backend.mechanics import LOAD_TORQUE
from sim_backend.drive_model import DriveModel
from sim_backend.twin_tube import (BLIND_SPEED, COMPARED, ESTIMATES, TIME_TOL_S, TOLERANCES, TubeResult,
                                   blind_rows, tube, tube_bounds)

RECORD = "record.json"
TELEMETRY = "telemetry.parquet"

# injections a replay cannot repeat: the device's and the wire's faults act on the rig, not on the motor and firmware
NOT_REPLAYED_PREFIXES = ("fault_",)


@dataclass(frozen=True)
class Injection:
    at_s: float
    name: str
    value: float


@dataclass
class RecordedRun:
    run_dir: Path
    record: dict[str, Any]
    t: np.ndarray                                  # drive clock of the rows replayed, s
    columns: dict[str, np.ndarray]                 # recorded signals (NaN where not measured), at t
    injections: list[Injection]
    injections_source: str                         # "record", "scenario" or "none"
    motor_path: Path | None                        # the bench's [simulator] motor, when it names one
    notes: list[str] = field(default_factory=list)
    instruments: "Instruments | None" = None       # the rig's reference sensors, when its bench config states them

    def measured(self, name: str) -> bool:
        values = self.columns.get(name)
        return values is not None and bool(np.isfinite(values).any())


def repo_root() -> Path:
    return Path(__file__).resolve().parents[1]


def _resolve(path: str | Path, *bases: Path) -> Path:
    p = Path(path)
    if p.is_absolute():
        return p
    for base in bases:
        if (base / p).exists():
            return base / p
    return p


def read_run(run_dir: str | Path) -> RecordedRun:
    """Read a run directory; InputError names the file and field that cannot be used."""
    run_dir = Path(run_dir)
    record_path = run_dir / RECORD
    try:
        record = json.loads(record_path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"{record_path}: (file): not found (not a run directory?)") from None
    except (OSError, ValueError) as exc:
        raise InputError(f"{record_path}: (file): unreadable: {exc}") from None
    if not isinstance(record, dict):
        raise InputError(f"{record_path}: (file): not a run record (a JSON object is expected)")
    parquet = run_dir / TELEMETRY
    try:
        table = pq.read_table(parquet)
    except FileNotFoundError:
        raise InputError(f"{parquet}: (file): not found (the run did not finish; `drivebench show` recovers "
                             f"its journal)") from None
    except (OSError, pa.ArrowException) as exc:
        raise InputError(f"{parquet}: (file): not a readable Parquet file: {' '.join(str(exc).split())[:160]}") \
            from None
    if TIME_COLUMN not in table.column_names:
        raise InputError(f"{parquet}: {TIME_COLUMN}: column missing: not drivebench telemetry")
    try:
        raw = {n: table.column(n).to_numpy().astype(np.float64) for n in table.column_names
               if n == TIME_COLUMN or n in SIGNAL_NAMES}
    except (TypeError, ValueError, pa.ArrowException) as exc:
        raise InputError(f"{parquet}: (file): not numeric telemetry: {exc}") from None
    t = raw.pop(TIME_COLUMN)
    if t.size < 2 or not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
        raise InputError(f"{parquet}: {TIME_COLUMN}: needs at least two rows on a strictly increasing drive clock")
    scenario = record.get("scenario") if isinstance(record.get("scenario"), dict) else {}
    duration = scenario.get("duration_s")
    keep = t <= float(duration) + 1e-9 if isinstance(duration, (int, float)) else np.ones(t.size, bool)
    keep &= t >= 0.0
    t = t[keep]
    columns = {n: v[keep] for n, v in raw.items()}
    if t.size < 2:
        raise InputError(f"{parquet}: {TIME_COLUMN}: fewer than two rows within the scenario's duration")
    if "speed_ref_mech_rad_s" not in columns or not np.isfinite(columns["speed_ref_mech_rad_s"]).any():
        raise InputError(f"{parquet}: speed_ref_mech_rad_s: not recorded (the twin replays the reference as the "
                             f"drive received it)")
    notes: list[str] = []
    if "torque_load_nm" not in columns or not np.isfinite(columns["torque_load_nm"]).any():
        notes.append("torque_load_nm not measured: replayed without load")
    injections, source = _injections(record, record_path, notes)
    motor_path, instruments = _bench_motor(record, notes)
    if instruments is not None:
        notes.append(instruments.describe())
    return RecordedRun(run_dir, record, t, columns, injections, source, motor_path, notes, instruments)


def _injections(record: dict, record_path: Path, notes: list[str]) -> tuple[list[Injection], str]:
    applied = record.get("injections_applied")
    if isinstance(applied, list):
        out = []
        for i, item in enumerate(applied):
            try:
                at = item.get("applied_t_s", item["at_s"])
                out.append(Injection(float(at), str(item["name"]), float(item["value"])))
            except (AttributeError, KeyError, TypeError, ValueError):
                raise InputError(f"{record_path}: injections_applied[{i}]: expected at_s, name and value") \
                    from None
        return out, "record"
    scenario = record.get("scenario") if isinstance(record.get("scenario"), dict) else {}
    path = scenario.get("path")
    if not path:
        notes.append("the record names no scenario: no injections replayed")
        return [], "none"
    path = _resolve(path, Path.cwd(), repo_root())
    try:
        data = path.read_bytes()
    except OSError:
        notes.append(f"scenario {path} not readable: no injections replayed")
        return [], "none"
    if scenario.get("sha256") and hashlib.sha256(data).hexdigest() != scenario["sha256"]:
        notes.append(f"scenario {path} changed since the run (sha256 differs): its injections are not replayed")
        return [], "none"
    try:
        items = tomllib.loads(data.decode("utf-8")).get("injection", [])
        out = [Injection(float(x["at_s"]), str(x["name"]), float(x["value"])) for x in items]
    except (tomllib.TOMLDecodeError, UnicodeDecodeError, AttributeError, KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{path}: injection: cannot be read: {exc}") from None
    return sorted(out, key=lambda inj: inj.at_s), "scenario"   # stable: same-time injections keep file order


def _bench_motor(record: dict, notes: list[str]) -> tuple[Path | None, Instruments | None]:
    bench = record.get("bench") if isinstance(record.get("bench"), dict) else {}
    path = bench.get("path")
    if not path:
        return None, None
    path = _resolve(path, Path.cwd(), repo_root())
    try:
        cfg = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError):
        notes.append(f"bench config {path} not readable: give the motor with --motor")
        return None, None
    instruments = _instruments(cfg, path)
    motor = (cfg.get("simulator") or {}).get("motor")
    if not motor:
        return None, instruments
    return _resolve(motor, Path.cwd(), repo_root(), path.parent), instruments


@dataclass(frozen=True)
class Instruments:
    """A rig's reference sensors as its bench config states them ([simulator.instruments] of an instruments rig,
    sim_backend/instruments.py; on a real rig the same figures from the encoder's and the transducer's data sheets).

    - encoder speed (M-method): counts over the last `encoder_speed_gate_s`, read every `reading_period_s` (the SYNC)
      and interpolated onto the rows: the twin's shaft speed is shown through the same gate and reading instants, and
      its tube is widened by one count over the gate (2 pi / counts_per_rev / gate: 0.153 rad/s at 4096 cpr, 10 ms);
    - torque transducer in line between motor and dynamometer: it reads T_L + J_dyno dw/dt through a first-order
      `torque_bandwidth_hz` lag. The twin's plant carries the whole shaft's inertia (dyno rotor included), so the
      replayed load is the reading minus J_dyno times the recorded encoder speed's slope (advanced by half a gate,
      through the same lag): the fitted J is then the whole shaft's, as the motor file means it.
    """
    encoder_counts_per_rev: float = 0.0            # 0: the shaft speed is not an encoder's reading
    encoder_speed_gate_s: float = 0.0
    torque_bandwidth_hz: float = 0.0               # 0: no lag
    dyno_inertia_kgm2: float = 0.0
    reading_period_s: float = 0.01

    @property
    def speed_count_rad_s(self) -> float:
        if self.encoder_counts_per_rev <= 0 or self.encoder_speed_gate_s <= 0:
            return 0.0
        return 2.0 * math.pi / self.encoder_counts_per_rev / self.encoder_speed_gate_s

    def describe(self) -> str:
        return (f"instruments: encoder {self.encoder_counts_per_rev:g} counts/rev over a "
                f"{self.encoder_speed_gate_s * 1e3:g} ms gate read every {self.reading_period_s * 1e3:g} ms (one count "
                f"= {self.speed_count_rad_s:.3g} rad/s); torque transducer {self.torque_bandwidth_hz:g} Hz reading the "
                f"dyno rotor's J_dyno = {self.dyno_inertia_kgm2:g} kg m^2 (subtracted from the replayed load)")


def _instruments(cfg: dict, path: Path) -> Instruments | None:
    table = (cfg.get("simulator") or {}).get("instruments")
    if not isinstance(table, dict):
        return None
    sync = (cfg.get("drive") or {}).get("sync_period_s", 0.01)
    try:
        return Instruments(float(table.get("encoder_counts_per_rev", 0.0)),
                           float(table.get("encoder_speed_gate_s", 0.0)),
                           float(table.get("torque_bandwidth_hz", 0.0)), float(table.get("dyno_inertia_kgm2", 0.0)),
                           float(sync))
    except (TypeError, ValueError) as exc:
        raise InputError(f"{path}: simulator.instruments: {exc}") from None


def encoder_view(t: np.ndarray, speed: np.ndarray, inst: Instruments) -> np.ndarray:
    """A shaft speed as the encoder reads it: the angle's change over the last gate, at the reading instants,
    interpolated onto the rows (as the bench records a reference sensor's readings)."""
    ok = np.isfinite(speed)
    if inst.encoder_speed_gate_s <= 0 or not ok.all():
        return speed
    angle = np.concatenate(([0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * np.diff(t))))
    tk = np.arange(math.ceil(t[0] / inst.reading_period_s - 1e-9), math.floor(t[-1] / inst.reading_period_s + 1e-9)
                   + 1) * inst.reading_period_s
    gate = inst.encoder_speed_gate_s
    wk = (np.interp(tk, t, angle) - np.interp(tk - gate, t, angle, left=0.0)) / gate
    return np.interp(t, tk, wk)


def dyno_torque(run: RecordedRun) -> np.ndarray:
    """What the transducer's reading holds of the dynamometer rotor's acceleration: J_dyno dw/dt of the recorded
    encoder speed (advanced by half a gate: its lag), through the transducer's first-order lag."""
    inst = run.instruments
    n = run.t.size
    if inst is None or inst.dyno_inertia_kgm2 <= 0 or not run.measured("speed_true_mech_rad_s"):
        return np.zeros(n)
    speed = _held(run.columns["speed_true_mech_rad_s"], n)
    acc = np.gradient(speed, run.t)
    dt = float(np.median(np.diff(run.t)))
    k = int(round(0.5 * inst.encoder_speed_gate_s / dt))
    if k:
        acc = np.concatenate((acc[k:], np.full(k, acc[-1])))
    torque = inst.dyno_inertia_kgm2 * acc
    if inst.torque_bandwidth_hz > 0:
        alpha = 1.0 - math.exp(-2.0 * math.pi * inst.torque_bandwidth_hz * dt)
        torque = lfilter([alpha], [1.0, alpha - 1.0], torque)
    return torque


# ---- motor files -----------------------------------------------------------------------------------------------

def read_motor(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    try:
        cfg = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"{path}: (file): not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: (file): unreadable: {exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{path}: (file): not TOML: {exc}") from None
    kind = (cfg.get("motor") or {}).get("kind") if isinstance(cfg.get("motor"), dict) else None
    if kind not in ("pmsm", "spim"):
        raise InputError(f"{path}: motor.kind: expected 'pmsm' or 'spim', got {kind!r}")
    return cfg


def build_drive(cfg: dict[str, Any], seed: int = 0, noise: bool = False, where: str = "motor") -> DriveModel:
    """The simulated drive of a motor config (the same constructors sim_backend.drive.make_drive dispatches to)."""
    try:
        if cfg["motor"]["kind"] == "pmsm":
            from sim_backend.pmsm.model import PmsmDrive
            return PmsmDrive.from_config(cfg, seed, noise=noise)
        from sim_backend.spim.model import SpimDrive
        return SpimDrive.from_config(cfg, seed, noise=noise)
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{where}: {exc}") from None


def get_key(cfg: dict[str, Any], dotted: str) -> float:
    section, key = dotted.split(".", 1)
    return float(cfg[section][key])


def with_values(cfg: dict[str, Any], values: dict[str, float]) -> dict[str, Any]:
    """A copy of a motor config with some dotted keys (`plant.rs_ohm`) replaced."""
    out = {k: dict(v) if isinstance(v, dict) else v for k, v in cfg.items()}
    for dotted, value in values.items():
        section, key = dotted.split(".", 1)
        out[section][key] = float(value)
    return out


# ---- replay ----------------------------------------------------------------------------------------------------

def _held(values: np.ndarray | None, n: int, default: float = 0.0) -> np.ndarray:
    """A recorded input with its gaps (NaN) filled by the last value before them."""
    if values is None or not np.isfinite(values).any():
        return np.full(n, default)
    v = values.copy()
    ok = np.isfinite(v)
    first = int(np.argmax(ok))
    v[:first] = v[first]
    idx = np.where(np.isfinite(v), np.arange(n), 0)
    np.maximum.accumulate(idx, out=idx)
    return v[idx]


def replay(cfg: dict[str, Any], run: RecordedRun, *, noise: bool = False, seed: int | None = None,
           where: str = "motor") -> dict[str, np.ndarray]:
    """The twin's telemetry at the recorded rows' times (one column per signal of drivers.contract.signals)."""
    drive = build_drive(cfg, run.record.get("seed", 0) if seed is None else seed, noise, where)
    period = drive.control_period_s
    n = run.t.size
    steps = np.rint(run.t / period).astype(np.int64)
    off_grid = "rows off the motor file's control period: each is compared with the period nearest to it"
    if np.any(np.abs(steps * period - run.t) > 0.25 * period) and off_grid not in run.notes:
        run.notes.append(off_grid)             # a drive clock of another rate; rows closer than a period share one
    ref = _held(run.columns.get("speed_ref_mech_rad_s"), n)
    load = _held(run.columns.get("torque_load_nm"), n) - dyno_torque(run)
    pending = [(int(math.ceil(inj.at_s / period - 1e-9)), inj) for inj in run.injections
               if not inj.name.startswith(NOT_REPLAYED_PREFIXES)]
    out = np.full((n, len(SIGNAL_NAMES)), np.nan)
    drive.set_enabled(True)
    done = 0                                             # model periods run; the next row out is period done + 1
    for i in range(n):
        drive.set_speed_ref(float(ref[i]))
        drive.set_load(LOAD_TORQUE, float(load[i]), True)
        target = int(steps[i])
        if target <= done and i > 0:
            out[i] = out[i - 1]
        while done < target:
            while pending and pending[0][0] <= done:
                _apply(drive, pending.pop(0)[1])
            stop = min(target, pending[0][0]) if pending and pending[0][0] > done else target
            block = drive.step(stop - done)
            done = stop
            out[i] = block[-1]
    twin = {name: out[:, c] for c, name in enumerate(SIGNAL_NAMES)}
    if run.instruments is not None and run.measured("speed_true_mech_rad_s"):
        twin["speed_true_mech_rad_s"] = encoder_view(run.t, twin["speed_true_mech_rad_s"], run.instruments)
    return twin


def _apply(drive: DriveModel, inj: Injection) -> None:
    try:
        if inj.name.startswith("plant_") or inj.name.startswith("inverter_"):
            drive.set_plant_param(inj.name, inj.value)
        else:
            drive.set_hook(inj.name, inj.value)
    except (KeyError, ValueError) as exc:
        raise InputError(f"{RECORD}: injections: {inj.name} = {inj.value:g} at {inj.at_s:g} s: the twin cannot "
                             f"apply it ({' '.join(str(exc).split())[:200]})") from None


def not_replayed(run: RecordedRun) -> list[str]:
    return sorted({inj.name for inj in run.injections if inj.name.startswith(NOT_REPLAYED_PREFIXES)})


# ---- the tube (sim_backend/twin_tube.py) around the recorded signals -------------------------------------------

def compare(run: RecordedRun, twin: dict[str, np.ndarray], tolerances: dict[str, float] | None = None,
            time_tol_s: float = TIME_TOL_S, blind_speed: float = BLIND_SPEED, kind: str = "pmsm") -> list[TubeResult]:
    defaults = dict(TOLERANCES.get(kind, COMPARED))
    if run.instruments is not None:             # an encoder reading is off by up to one count over its gate
        defaults["speed_true_mech_rad_s"] += run.instruments.speed_count_rad_s
    tolerances = {**defaults, **(tolerances or {})}
    est = "speed_est_mech_rad_s"
    blind = blind_rows(run.t, [run.columns[est], twin[est]] if run.measured(est) else [], blind_speed)
    return [tube(name, run.t, run.columns[name], twin[name], time_tol_s, tol, blind if name in ESTIMATES else None)
            for name, tol in tolerances.items() if run.measured(name)]


def plot(run: RecordedRun, twin: dict[str, np.ndarray], results: list[TubeResult], path: Path,
         title: str = "") -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(results), 1, figsize=(11, 2.2 * len(results) + 0.6), sharex=True, squeeze=False)
    for ax, res in zip(axes[:, 0], results):
        lo, hi = tube_bounds(run.t, run.columns[res.signal], res.time_tol_s, res.value_tol)
        ax.fill_between(run.t, lo, hi, color="tab:blue", alpha=0.25, lw=0, label="tube around the record")
        ax.plot(run.t, run.columns[res.signal], color="tab:blue", lw=0.7, label="recorded")
        ax.plot(run.t, twin[res.signal], color="tab:red", lw=0.7, label="twin")
        for a, b in res.intervals_outside:
            ax.axvspan(a, max(b, a + 1e-3), color="tab:red", alpha=0.15, lw=0)
        if res.not_compared_s > 0:
            ax.text(0.995, 0.04, f"not compared near zero speed: {res.not_compared_s:.3f} s", ha="right",
                    transform=ax.transAxes, fontsize=7, color="0.4")
        state = "inside" if res.inside else f"outside {res.fraction_outside:.1%}, max {res.max_excess:.3g}"
        ax.set_ylabel(res.signal, fontsize=8)
        ax.set_title(f"{res.signal}: {state} (tube +-{res.value_tol:g}, +-{res.time_tol_s * 1e3:g} ms)", fontsize=9,
                     loc="left")
        ax.grid(alpha=0.3)
    axes[0, 0].legend(loc="upper right", fontsize=7)
    axes[-1, 0].set_xlabel("drive clock t_s (s)")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
