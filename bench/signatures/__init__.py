"""Drawn shaft signatures (issue 36, docs/shaft-signatures.md): points a firmware cannot anticipate, drawn from the
run's seed, each with the prediction the papers' equations give from the motor data."""
