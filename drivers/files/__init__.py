"""The files stage: a vendor's EDS or DCF read the way its own tools read it, what the drive
can do according to it, and which device (0x1018) it describes.

Read once at start-up and by ``check-config``; nothing here touches a bus."""
