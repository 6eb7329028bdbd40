"""The simulated drive's CANopen node: node (wiring, SYNC, EMCY), drive_objects (what the objects mean), pdo (the PDO
engine), block_server (SDO block upload), heartbeat, virtual_bus (the fast virtual bus)."""
