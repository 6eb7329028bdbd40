"""The CANopen contract shared by the bench's client and the simulated node: object indices, COB-IDs, data types,
SDO block-transfer command bytes and abort codes (CiA 301, CiA 402), and drivebench's extension objects.

The extension objects (0x2000-0x24FF) are drivebench's manufacturer range: a bench uses them only on a drive whose
identity says it carries the extension (drivers.contract.extension), never because an index exists in an EDS.
"""

from __future__ import annotations

# -- CiA 301 communication objects --------------------------------------------------------------------------------
DEVICE_TYPE = 0x1000
ERROR_REGISTER = 0x1001
COB_ID_SYNC = 0x1005
COMM_CYCLE_PERIOD = 0x1006          # us
DEVICE_NAME = 0x1008
HARDWARE_VERSION = 0x1009
SOFTWARE_VERSION = 0x100A
COB_ID_EMCY = 0x1014
CONSUMER_HEARTBEAT = 0x1016         # sub n: node id << 16 | time in ms
PRODUCER_HEARTBEAT = 0x1017         # ms
IDENTITY = 0x1018                   # sub 1 vendor, 2 product, 3 revision, 4 serial
ERROR_BEHAVIOUR = 0x1029            # sub 1: communication error -> 0 pre-operational, 1 no change, 2 stopped
SDO_SERVER = 0x1200
RPDO_COMM, RPDO_MAP = 0x1400, 0x1600
TPDO_COMM, TPDO_MAP = 0x1800, 0x1A00
N_RPDO_MAX, N_TPDO_MAX = 4, 8       # what the bench plans with (predefined connection set + 4 CANopenNode TPDOs)

# -- CiA 402 objects ----------------------------------------------------------------------------------------------
ABORT_CONNECTION_OPTION = 0x6007    # reaction to a lost master (heartbeat/NMT/bus off): 1 fault, 2 disable voltage, 3 quick stop
ABORT_CONNECTION_CODES = {0: "no action", 1: "fault", 2: "disable voltage", 3: "quick stop"}
ERROR_CODE = 0x603F
CONTROLWORD = 0x6040
STATUSWORD = 0x6041
QUICK_STOP_OPTION = 0x605A
MODES_OF_OPERATION = 0x6060
MODES_DISPLAY = 0x6061
POSITION_ACTUAL = 0x6064            # position units (0x60A8 / 0x608F)
VELOCITY_DEMAND = 0x606B            # velocity units (0x60A9): the reference after the drive's ramp
VELOCITY_ACTUAL = 0x606C            # velocity units (0x60A9)
MOTOR_RATED_CURRENT = 0x6075        # mA
MOTOR_RATED_TORQUE = 0x6076         # mN*m
TORQUE_ACTUAL = 0x6077              # per mille of 0x6076
CURRENT_ACTUAL = 0x6078             # per mille of 0x6075
DC_LINK_VOLTAGE = 0x6079            # mV
POSITION_ENCODER_RESOLUTION = 0x608F
VELOCITY_ENCODER_RESOLUTION = 0x6090
GEAR_RATIO = 0x6091                 # sub 1 motor revolutions, sub 2 shaft revolutions
FEED_CONSTANT = 0x6092
SI_UNIT_POSITION = 0x60A8
SI_UNIT_VELOCITY = 0x60A9
TARGET_VELOCITY = 0x60FF            # velocity units (0x60A9)
SUPPORTED_DRIVE_MODES = 0x6502

# -- COB-IDs (predefined connection set) ------------------------------------------------------------------------
NMT = 0x000
SYNC = 0x080
EMCY = 0x080                        # + node id
TPDO_COB = (0x180, 0x280, 0x380, 0x480, 0x1C0, 0x2C0, 0x3C0, 0x4C0)   # 5-8: CANopenNode convention, +0x40
RPDO_COB = (0x200, 0x300, 0x400, 0x500)
SDO_TX = 0x580                      # server -> client, + node id
SDO_RX = 0x600                      # client -> server, + node id
HEARTBEAT = 0x700                   # + node id
COB_ID_INVALID = 0x80000000         # bit 31 of a PDO communication parameter's COB-ID: PDO does not exist / invalid
COB_ID_NO_RTR = 0x40000000

HEARTBEAT_BENCH_NODE_ID = 0x7F      # the bench's own heartbeat (master), 0x77F, consumed by the drive (0x1016)

# NMT states as a heartbeat carries them
NMT_BOOT_UP, NMT_STOPPED, NMT_OPERATIONAL, NMT_PRE_OPERATIONAL = 0x00, 0x04, 0x05, 0x7F

# -- data types (CiA 301 Table 44) ------------------------------------------------------------------------------
BOOLEAN, INTEGER8, INTEGER16, INTEGER32 = 0x1, 0x2, 0x3, 0x4
UNSIGNED8, UNSIGNED16, UNSIGNED32, REAL32, VISIBLE_STRING, DOMAIN = 0x5, 0x6, 0x7, 0x8, 0x9, 0xF

# -- SDO --------------------------------------------------------------------------------------------------------
SDO_ABORT = 0x80
BLOCK_UPLOAD_INITIATE = 0xA0        # client: ccs 5, + BLOCK_CRC_SUPPORTED
BLOCK_UPLOAD_END = 0xA1             # client: end of transfer confirmed
BLOCK_UPLOAD_ACK = 0xA2             # client: ackseq, blksize
BLOCK_UPLOAD_START = 0xA3           # client: start sending segments
BLOCK_CRC_SUPPORTED = 0x04
BLOCK_SIZE_INDICATED = 0x02
BLOCK_RESPONSE_INITIATE = 0xC0      # server: scs 6, + CRC / size flags
BLOCK_RESPONSE_END = 0xC1           # server: + unused bytes << 2, CRC in bytes 1-2
BLOCK_SUBCOMMAND_MASK = 0x03        # server side: 0 initiate, 1 end, 2 ack, 3 start
BLOCK_LAST_SEGMENT = 0x80
MAX_BLOCK_SIZE = 127                # segments per sub-block
SEGMENT_DATA = 7                    # data bytes per segment

ABORT_TOGGLE = 0x05030000
ABORT_TIMEOUT = 0x05040000
ABORT_COMMAND = 0x05040001
ABORT_BLOCK_SIZE = 0x05040002
ABORT_SEQUENCE = 0x05040003
ABORT_CRC = 0x05040004
ABORT_READ_ONLY = 0x06010002
ABORT_NOT_IN_OD = 0x06020000
ABORT_CANNOT_MAP = 0x06040041
ABORT_PDO_TOO_LONG = 0x06040042
ABORT_INVALID_VALUE = 0x06090030
ABORT_GENERAL = 0x08000000
ABORT_NO_DATA = 0x08000024

# -- EMCY -------------------------------------------------------------------------------------------------------
EMCY_OVERCURRENT = 0x2310
EMCY_PDO_LENGTH = 0x8210            # PDO not processed due to length error
EMCY_HEARTBEAT = 0x8130             # life guard / heartbeat error

# -- drivebench extension objects (drivers.contract.extension) ------------------------------------------------------------
EXT_STEP_COUNT = 0x2000             # drive clock: control periods since power-up, UNSIGNED32
EXT_CONTROL_PERIOD_NS = 0x2001
EXT_DRIVE_KIND = 0x2002
EXT_SIGNAL_BASE = 0x2010            # live telemetry, REAL32, one per drivers.contract.signals.SIGNAL_NAMES entry
EXT_SCALED_BASE = 0x2030            # the same as INTEGER16, value = raw * EDS Factor
SCALED_PREFIX = "scaled_"
EXT_TRACE = 0x2100                  # trace recorder configuration record (TRACE_SUBS)
EXT_TRACE_DATA = 0x2101             # DOMAIN: oldest recorded rows (drivers.contract.trace_format), SDO block upload
TRACE_SUBS = {  # subindex: (name, data type, access)
    1: ("trace_signal_mask", UNSIGNED32, "rw"),
    2: ("trace_decimation", UNSIGNED16, "rw"),
    3: ("trace_trigger", UNSIGNED8, "rw"),
    4: ("trace_control", UNSIGNED8, "rw"),          # write TRACE_STOP / TRACE_START / TRACE_CLEAR
    5: ("trace_rows_available", UNSIGNED32, "ro"),
    6: ("trace_row_size", UNSIGNED16, "ro"),
    7: ("trace_lost_rows", UNSIGNED32, "ro"),
    8: ("trace_capacity_rows", UNSIGNED32, "ro"),
    9: ("trace_max_rows_per_upload", UNSIGNED32, "rw"),
}
TRACE_MASK, TRACE_DECIMATION, TRACE_TRIGGER, TRACE_CONTROL = 1, 2, 3, 4
TRACE_ROWS_AVAILABLE, TRACE_ROW_SIZE, TRACE_LOST_ROWS, TRACE_CAPACITY, TRACE_MAX_ROWS = 5, 6, 7, 8, 9
TRACE_STOP, TRACE_START, TRACE_CLEAR = 0, 1, 2
# parameter objects (drivers.contract.parameters), REAL32 rw, one block per parameter kind, in catalogue order
EXT_HOOK_BASE = 0x2200
EXT_FIRMWARE_BASE = 0x2300
EXT_PLANT_BASE = 0x2400
EXT_FAULT_BASE = 0x2480             # device and wire faults
EXT_PARAMETER_RANGE = range(EXT_HOOK_BASE, 0x2500)
MANUFACTURER_RANGE = range(0x2000, 0x6000)


def signal_index(i: int) -> int:
    return EXT_SIGNAL_BASE + i


def mapping_entry(index: int, subindex: int, bits: int) -> int:
    """A PDO mapping parameter entry: index << 16 | subindex << 8 | length in bits."""
    return index << 16 | subindex << 8 | bits


def unpack_mapping_entry(raw: int) -> tuple[int, int, int]:
    return raw >> 16, (raw >> 8) & 0xFF, raw & 0xFF
