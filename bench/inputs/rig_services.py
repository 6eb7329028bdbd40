"""A rig config's [services] starters (the code that brings up a simulated rig's servers; not the HTTP service,
bench/service/): [services] start runs code, so only starters installed
packages register (entry-point group drivebench.services) are accepted, by name or by their "module:function"."""

from __future__ import annotations

from functools import cache

from drivers.contract.errors import InputError

SERVICE_GROUP = "drivebench.services"


@cache
def registered_services() -> dict[str, str]:
    """{name: "module:function"} of the service starters installed packages register (entry-point group
    drivebench.services; drivebench itself registers sim = sim_backend.rig:start). Read once per process: the scan
    of every installed distribution took about 3 ms of each bench config read (prepare_run 5.4 -> 2.5 ms)."""
    from importlib.metadata import entry_points

    return {entry.name: entry.value for entry in entry_points(group=SERVICE_GROUP)}


def registered_service(spec: str, where: str) -> str:
    try:
        return _registered(spec)
    except ValueError as exc:
        raise InputError([f"{where}: {exc}"]) from None


def check_service(spec: str) -> str | None:
    """None when spec names a registered starter, else the reason."""
    try:
        _registered(spec)
        return None
    except ValueError as exc:
        return str(exc)


def _registered(spec: str) -> str:
    """A bench config names code the bench will run: only a registered starter, by its name or its
    "module:function", never an arbitrary module (a bench config from elsewhere must not execute code)."""
    known = registered_services()
    if spec in known:
        return known[spec]
    if spec in known.values():
        return spec
    choices = ", ".join(f"{name} ({value})" for name, value in sorted(known.items())) or "none installed"
    raise ValueError(f"{spec!r} is not a registered service starter (entry-point group {SERVICE_GROUP}: {choices})")


WARM_UP_GROUP = "drivebench.warm_ups"


def warm_up_for(spec: str) -> str | None:
    """The "module:function" that warms a process for the starter `spec` names (registered under the same name in
    entry-point group drivebench.warm_ups: sim = sim_backend.rig:warm_up), or None."""
    from importlib.metadata import entry_points

    try:
        value = _registered(spec)
    except ValueError:
        return None
    names = [name for name, known in registered_services().items() if known == value]
    warm = {entry.name: entry.value for entry in entry_points(group=WARM_UP_GROUP)}
    return next((warm[name] for name in names if name in warm), None)
