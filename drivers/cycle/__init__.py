"""The cycle stage: what the hardware does once per control cycle, on the loop's thread.

Every part takes the one drive table (drive_table: each drive's plan, bus and node, built
once at start-up). read: receive (every queued frame by COB-ID), supervision (every
symptom -> one FaultEvent), node_guarding, status, homing; what the manager must act on is a
stop request (stop_requests, which collects a read's findings). write: command
(JointCommand -> controlword, mode, targets), enable (the CiA 402 enable sequence),
frames_out (every frame sent, torque-off first: the safety path's last step). Off the
cycle, driven from it: recovery and switch_off."""
