"""What a run is made of: scenario files and their criteria, bench configs, the [services] starters they name,
and the run prepared from them once."""
