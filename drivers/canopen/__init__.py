"""The bench's CANopen CiA 402 client: object map (objects), bus set-up (bus), SDO access and block upload (sdo),
live PDO planning and decoding (pdo), SYNC production (sync) and the DriveLink (link)."""
