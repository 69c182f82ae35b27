"""``rocoma-can demo``: the whole system on in-process CAN buses, walked through by an
operator that talks to the manager only as another CAN node would. command (the verb: its
options and exit code), walkthrough (the run, a step per method: config, drives, runtime,
the walk beside the loop, the judgement, the plot), steps (the walk-through's steps),
config (its drives and config, fitted to a vendor file with --eds), drives (its simulated
drives, stepped by the loop or in a process of their own), probe (its check of the loop's
torque-off frames), stops (an operator's e-stop ends its walk-through) and report (what it
says: steps, notes, status lines, summary, plot)."""
