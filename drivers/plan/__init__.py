"""The plan stage: what rocoma-can will do with each drive, decided before a frame is sent.

A drive's config (DriveConfig, BusConfig) measured against its device file becomes a plan:
the PDO layouts, the modes each joint is commanded in, the unit scaling and the drive-side
limits; the checks across drives (drive_clashes). Computed once; the cycle only reads it."""
