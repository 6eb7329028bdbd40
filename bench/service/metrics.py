"""GET /metrics: the service in Prometheus's text format (prometheus_client), read from the database at each
scrape — queue length and the oldest queued run's wait per rig or tag, runs by state and by verdict, active leases
by kind, lease events (created, released, expired without release), run durations (a summary of finished runs)."""

from __future__ import annotations

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, SummaryMetricFamily
from prometheus_client.registry import CollectorRegistry
from sqlalchemy import func, select

from bench.service.db import STATES, Database, Lease, Run, now


class ServiceCollector:
    def __init__(self, db: Database):
        self.db = db

    def collect(self):
        t = now()
        with self.db.session() as s:
            by_state = dict(s.execute(select(Run.state, func.count()).group_by(Run.state)).all())
            queued = s.execute(select(func.coalesce(Run.rig, "tag:" + func.coalesce(Run.tag, "")), func.count(),
                                      func.min(Run.submitted_ts)).where(Run.state == "queued")
                               .group_by(func.coalesce(Run.rig, "tag:" + func.coalesce(Run.tag, "")))).all()
            verdicts = s.execute(select(Run.verdict, func.count()).where(Run.verdict.is_not(None))
                                 .group_by(Run.verdict)).all()
            active = s.execute(select(Lease.kind, func.count()).where(Lease.released_ts.is_(None),
                                                                       Lease.expires_ts > t)
                               .group_by(Lease.kind)).all()
            created = s.execute(select(func.count()).select_from(Lease)).scalar() or 0
            released = s.execute(select(func.count()).where(Lease.released_ts.is_not(None))
                                 .select_from(Lease)).scalar() or 0
            expired = s.execute(select(func.count()).where(Lease.released_ts.is_(None), Lease.expires_ts <= t)
                                .select_from(Lease)).scalar() or 0
            durations = s.execute(select(func.count(), func.coalesce(func.sum(Run.duration_s), 0.0))
                                  .where(Run.duration_s.is_not(None))).one()
        runs = GaugeMetricFamily("drivebench_runs", "Runs in the database by state", labels=["state"])
        for state in STATES:
            runs.add_metric([state], by_state.get(state, 0))
        yield runs
        length = GaugeMetricFamily("drivebench_queue_length", "Queued runs per rig (or tag:NAME for runs by tag)",
                                   labels=["target"])
        wait = GaugeMetricFamily("drivebench_queue_oldest_wait_seconds",
                                 "How long the oldest queued run per rig or tag has waited", labels=["target"])
        for target, count, oldest in queued:
            length.add_metric([target], count)
            wait.add_metric([target], max(0.0, t - oldest))
        yield length
        yield wait
        verdict = CounterMetricFamily("drivebench_run_verdicts", "Finished runs by verdict", labels=["verdict"])
        for name, count in verdicts:
            verdict.add_metric([name], count)
        yield verdict
        leases = GaugeMetricFamily("drivebench_leases_active", "Active leases by kind (run, manual)", labels=["kind"])
        for kind, count in active:
            leases.add_metric([kind], count)
        yield leases
        events = CounterMetricFamily("drivebench_lease_events", "Lease events since the database was created",
                                     labels=["event"])
        events.add_metric(["created"], created)
        events.add_metric(["released"], released)
        events.add_metric(["expired_unreleased"], expired)
        yield events
        yield SummaryMetricFamily("drivebench_run_duration_seconds", "Wall time of finished runs",
                                  count_value=durations[0], sum_value=float(durations[1]))


def registry_for(db: Database) -> CollectorRegistry:
    registry = CollectorRegistry(auto_describe=False)
    registry.register(ServiceCollector(db))
    return registry
