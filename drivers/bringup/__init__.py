"""The bring-up stage: each drive from boot-up to operation enabled, by a non-blocking state
machine stepped once per cycle (SDO configuration runs on worker threads), and what bring-up
tells a person about it."""
