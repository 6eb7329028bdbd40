"""Simulated drives (plant, inverter, firmware) and the protocol servers in front of them."""
