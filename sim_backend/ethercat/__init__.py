"""A simulated EtherCAT slave: an ESC (register space, SyncManagers, FMMUs, SII EEPROM, AL state machine, SM
watchdog) in front of a CoE CiA 402 drive, answering real EtherCAT frames (EtherType 0x88A4) on a raw socket."""
