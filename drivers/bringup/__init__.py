"""The bring-up stage: each drive from boot-up to READY (torque off), by a non-blocking state
machine stepped once per cycle (drive_bringup), its SDO configuration job on worker threads
(configure, through named_sdo), the start-up of every drive (start_up: the workers, the
stepping) and what bring-up tells a person about it (report)."""
