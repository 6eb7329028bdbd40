"""`requirements = ["REQ-12", ...]` in a scenario: the requirement ids the run gives evidence for, carried unchanged
into record.json (`scenario.requirements`), the JUnit properties and the report, so a lab's requirement tracker can
find the runs that test a requirement."""

from __future__ import annotations

from drivers.contract.checks import Problems

MAX_REQUIREMENTS = 100
MAX_ID_CHARS = 200


def parse_requirements(p: Problems, raw: dict) -> tuple[str, ...]:
    value = raw.get("requirements", [])
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        p.add("requirements", 'must be an array of requirement ids, e.g. requirements = ["REQ-12", "REQ-40"]')
        return ()
    if len(value) > MAX_REQUIREMENTS:
        p.add("requirements", f"{len(value)} ids: at most {MAX_REQUIREMENTS}")
        return ()
    ids = []
    for i, item in enumerate(value):
        text = item.strip()
        if not text or len(text) > MAX_ID_CHARS or any(c in text for c in "\n\r\t,"):
            p.add(f"requirements[{i}]", f"must be 1 to {MAX_ID_CHARS} characters without commas or line breaks, "
                                        f"got {item[:40]!r}")
        elif text in ids:
            p.add(f"requirements[{i}]", f"{text!r} is listed twice")
        else:
            ids.append(text)
    return tuple(ids)
