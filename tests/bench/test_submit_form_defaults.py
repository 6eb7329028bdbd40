"""The web submit form: its default target is a tag of the rigs file's first rig (it was the alphabetically first
tag, a drive of another kind, so the placeholder scenario failed), and a refused submission's page names files
relative to the repository, not by a host path."""

from __future__ import annotations

import re
from pathlib import Path

from tests.service_fixtures import client_for, make_settings

REPO = Path(__file__).resolve().parents[2]


def test_default_target_is_the_first_rigs_tag_and_errors_show_no_host_path(tmp_path):
    with client_for(make_settings(tmp_path)) as api:
        op = {"Authorization": f"Bearer {api.tokens.operator}"}
        page = api.get("/", headers=op).text
        options = re.findall(r'<option value="([^"]+)"', page)
        assert options[0] == "tag:pmsm", options          # sim-a (first in the rigs file): pmsm; not "lab"
        refused = api.post("/ui/runs", data={"scenario": "short.toml", "target": "rig:spim-a"}, headers=op,
                           follow_redirects=False)
        assert refused.status_code == 422
        assert "is for a PMSM drive" in refused.text and str(REPO) not in refused.text, refused.text
        bad = api.post("/ui/runs", data={"scenario": "bad.toml", "target": "rig:sim-a"}, headers=op,
                       follow_redirects=False)
        assert bad.status_code == 422 and str(REPO) not in bad.text, bad.text
