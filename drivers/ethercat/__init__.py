"""EtherCAT CoE drives through pysoem (SOEM): the master (master.py), ESI files (esi.py), the [drive] section
(config.py) and the CiA 402 drive link (link.py)."""
