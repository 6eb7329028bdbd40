"""Clients the bench uses against real drives, load machines and the simulator alike."""
