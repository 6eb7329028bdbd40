"""The run's periods and bounds (drive time unless said) and its live signal set, for the run modules."""

from __future__ import annotations

# Live (PDO) signals, judged by the supervisor every SYNC. Eight REAL32 fit a 1 Mbit/s CAN bus at one SYNC
# per ms within the links' 80 % budget; everything else comes from the trace recorder.
LIVE_SIGNALS: tuple[str, ...] = (
    "speed_ref_mech_rad_s", "speed_est_mech_rad_s", "speed_true_mech_rad_s", "pos_err_elec_rad",
    "i_sx_a", "i_sy_a", "vdc_v", "torque_load_nm",
)
MAX_DEFERRED_APPENDS = 8   # lockstep: trace blocks waiting for the journal writer before the command thread waits
FETCH_PERIOD_S = 0.25      # upload the trace recorder every 0.25 s of drive time (a killed bench loses at most that)
RERUN_MAX_RATE_HZ = 2000.0 # run.rrd / viewer: a 10 kHz trace is thinned to 2 kHz (3.6 -> 0.8 MB/s); parquet has all
STATUS_PERIOD_S = 0.02     # poll the drive's status (fault, EMCY, heartbeat) every 20 ms of drive time
PROGRESS_PERIOD_S = 0.1
STUCK_GRACE_S = 2.0        # after a trip, how long the run loop may take to notice before it is abandoned
SUPERVISE_POLL_S = 0.05    # the main thread's wait on the run loop (signals are handled between waits)
STALL_TIMEOUT_S = 5.0      # wall seconds without any live sample -> the link is dead
LOAD_POLL_PERIOD_S = 0.1   # read the load machine's status (fault bit; a dead Modbus link) every 0.1 s of drive time
FEEDBACK_LOST_PERIODS = 5  # real time: a measured live signal missing this many SYNC periods in a row trips
FEEDBACK_LOST_MIN_S = 0.5  # ... and no live sample at all for this long (or 5 periods, the longer): a loaded host
                           # stalls the bench's own threads for 40-80 ms, more under heavy load
