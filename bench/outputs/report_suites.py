"""The suites file of `drivebench report --suites FILE` (this repository's: config/report/paper-suites.toml): which
scenario folders are a suite of claims, the suite's title, deviations, appended sections and wording. Read once into a
frozen Suites; without a file every run is reported as what it is."""

from __future__ import annotations

import re
from dataclasses import dataclass, fields
from pathlib import Path

from drivers.contract.errors import InputError

OTHER = "other"


@dataclass(frozen=True)
class Wording:
    """What a suites file's [text] table may say instead of these neutral defaults."""
    other_heading: str = "Other scenarios"               # runs outside the suites' folders
    claim_heading: str = "limit / basis"                 # the criteria column of a suite's run
    seed_dependent_note: str = "passed with this run's seed, not with every seed"
    mutants_intro: str = ("Mutants found beside the runs (DIR/mutants/*.json) and the scenarios that rejected them; "
                          "a surviving mutant fails the suite.")
    deviations_heading: str = "Deviations"
    firmware_deviations_heading: str = "In the firmware"
    suite_deviations_heading: str = "In the suite"
    firmware_docs_glob: str = "firmware*.md"
    firmware_list_intro: str = r".*\bchosen:\s*$"        # a line introducing a list of choices (regex, per line)


@dataclass(frozen=True)
class Suites:
    """A suites file: scenario folders that are a suite of claims (this repository's papers:
    config/report/paper-suites.toml). Without one every run is reported as what it is: a scenario with its stated
    basis, no suite's claim."""
    title: str = "Test report"
    regenerate: str = ""
    folders: tuple[tuple[str, Path, str], ...] = ()      # (key, folder, heading)
    firmware_docs: Path | None = None
    deviations: tuple[str, ...] = ()
    sections: tuple[Path, ...] = ()                      # hand-written markdown appended as it is (e.g. rig form)
    text: Wording = Wording()

    def key_of(self, scenario_path: Path | None) -> str:
        if scenario_path is not None:
            for key, folder, _ in self.folders:
                if scenario_path.resolve().parent == folder:
                    return key
        return OTHER

    def heading(self, key: str) -> str:
        own = {k: title for k, _, title in self.folders}
        if key in own:
            return own[key]
        return self.text.other_heading if self.folders else "Runs"

    @property
    def keys(self) -> list[str]:
        return [k for k, _, _ in self.folders] + [OTHER]


def load_suites(path: str | Path | None) -> Suites:
    """The suites file, folders resolved against the repository root that holds it; InputError when unreadable."""
    if path is None:
        return Suites()
    from drivers.contract.checks import read_toml
    from drivers.contract.checks import find_repo_root

    path = Path(path)
    raw = read_toml(path)
    root = find_repo_root(path)
    problems = []
    folders = []
    for i, entry in enumerate(raw.get("suite") or []):
        folder, title = entry.get("folder"), entry.get("title")
        if not isinstance(folder, str) or not isinstance(title, str) or not (root / folder).is_dir():
            problems.append(f"{path}: suite[{i}]: needs a folder (an existing directory) and a title")
            continue
        folders.append((Path(folder).name, (root / folder).resolve(), title))
    docs = raw.get("firmware_docs")
    deviations = raw.get("deviations") or []
    if not isinstance(deviations, list) or not all(isinstance(d, str) for d in deviations):
        problems.append(f"{path}: deviations: must be a list of strings")
    sections = raw.get("sections") or []
    if not isinstance(sections, list) or not all(isinstance(f, str) and (root / f).is_file() for f in sections):
        problems.append(f"{path}: sections: must be a list of markdown files (paths from the repository root)")
    text = raw.get("text") or {}
    known = {f.name for f in fields(Wording)}
    if not isinstance(text, dict):
        problems.append(f"{path}: text: must be a table")
        text = {}
    problems += [f"{path}: text.{key}: unknown key (allowed: {', '.join(sorted(known))})" for key in text
                 if key not in known]
    problems += [f"{path}: text.{key}: must be a string" for key, value in text.items()
                 if key in known and not isinstance(value, str)]
    if isinstance(text.get("firmware_list_intro"), str):
        try:
            re.compile(text["firmware_list_intro"])
        except re.error as exc:
            problems.append(f"{path}: text.firmware_list_intro: not a regular expression ({exc})")
    if problems:
        raise InputError(problems)
    return Suites(str(raw.get("title") or "Validation report"), str(raw.get("regenerate") or ""), tuple(folders),
                  (root / docs) if isinstance(docs, str) else None, tuple(deviations),
                  tuple(root / f for f in sections), Wording(**text))
