"""Safety: the one supervisor (limits, leases, the e-stop latch), the FES limiter, the assistance map and the fault
policy. Qt-free; every command to a device passes here.
"""
