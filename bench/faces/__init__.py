"""How people and CI reach a run: the command line (and its probe checklist), campaigns and the pytest plugin (the HTTP service is bench.service)."""
