"""The commissioning stage: the first look at a robot's bus, before any config exists.

scan (every node on a bus, by SDO reads only) and LSS (CiA 305: node ids for nodes that have
none)."""
