"""`drivebench compare`'s text: what ran, what differs in the scenarios, each criterion in both runs with its limit,
each signal's difference, and the signals only one run measured."""

from __future__ import annotations

from typing import Any, Callable

from rich.table import Table


def print_comparison(result: dict, console, fmt: Callable[[Any], str]) -> None:
    console.print(f"A: {result['a']}\nB: {result['b']}")
    ident = Table(title="what ran", title_justify="left")
    for col in ("", "A", "B", ""):
        ident.add_column(col)
    for row in result["identity"]:
        ident.add_row(row["field"], fmt(row["a"]), fmt(row["b"]), "" if row["same"] else "[yellow]differs[/]")
    console.print(ident)
    if result.get("scenario"):
        scen = Table(title="scenario (what differs in the files that ran)", title_justify="left")
        for col in ("key", "A", "B", ""):
            scen.add_column(col)
        for row in result["scenario"]:
            scen.add_row(row["key"], fmt(row["a"]), fmt(row["b"]), row.get("note") or "")
        console.print(scen)
    crit = Table(title="criteria", title_justify="left")
    for col, justify in (("criterion", "left"), ("A", "right"), ("B", "right"), ("B - A", "right"),
                         ("unit", "left"), ("limit A", "right"), ("limit B", "right"), ("A / B", "left")):
        crit.add_column(col, justify=justify)
    for row in result["criteria"]:
        changed = row.get("changed") or []
        crit.add_row(str(row["name"]), fmt(row["value_a"]), fmt(row["value_b"]), fmt(row["delta"]), row["unit"],
                     fmt(row.get("limit_a")), fmt(row.get("limit_b")),
                     f"{row['status_a']} / {row['status_b']}"
                     + (f"  [yellow]{', '.join(changed)} changed[/]" if changed else ""))
    console.print(crit)
    sig = Table(title="signals (B - A over the common drive-clock span)", title_justify="left")
    for col, justify in (("signal", "left"), ("rms", "right"), ("max |B - A|", "right"), ("at [s]", "right"),
                         ("unit", "left")):
        sig.add_column(col, justify=justify)
    for row in result["signals"]:
        if row.get("only_in"):
            sig.add_row(row["signal"], f"[yellow]measured in {row['only_in'].upper()} only[/]", "", "", row["unit"])
        else:
            sig.add_row(row["signal"], fmt(row["rms_diff"]), fmt(row["max_abs_diff"]), fmt(row["at_s"]), row["unit"])
    console.print(sig)
    if result.get("plot"):
        console.print(f"plot: {result['plot']}")
