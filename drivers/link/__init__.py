"""The link stage: how frames get on and off a bus.

python-can buses with a canopen Network and one reader thread each, the hardware's view of
one bus (BusPort), cheap frame I/O for threads that see every frame, the in-process bus and
its link between two processes, and the SocketCAN link as the kernel reports it."""
