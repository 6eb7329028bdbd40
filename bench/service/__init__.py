"""The bench service (`drivebench serve`): HTTP API, run queue, leased rigs, tokens, history, live view.

Importing this package imports nothing heavy; the web stack is loaded by `bench.service.app`.
"""
