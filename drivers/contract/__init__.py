"""The device contract: what the bench, the drivers' clients and the simulated drives agree on, and nothing else.

Here: the CiA 402 state machine and sequences (cia402), the CANopen object map (objects), drivebench's extension
identity (extension), the parameter and signal catalogues (parameters, signals), the EDS reader both the link and the simulated node
load an object dictionary with (eds), units (units), the serial wire
format (serial_frames), the trace row format (trace_format), the load-machine register-map schema (load_map), the
comm-loss settings every transport applies (comm_loss), the error types (errors), the config-checking helpers and
the one TOML reader (checks, toml_file), the typed-section reader every config section is built with (sections),
the [simulator] section the bench validates and the simulator builds its rig from (simulator), the commands' exit
codes (exits) and the rate-limited log both sides' servers use (ratelog). Not here, in drivers/: the clients that
talk to a device (the CANopen, serial and Modbus links, the drive profile a CANopen link resolves,
the probe and drill, the link protocol the bench calls in drivers.api), each transport's typed config beside its
link, and the transport registry (drivers.transports). The contract imports nothing from drivers/ outside itself,
nor bench/ or sim_backend/ (tests/bench/test_structure.py); every other package may import it.
"""
