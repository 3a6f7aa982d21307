"""The wire: each device's protocol tables, codecs and constants. Pure (no Qt, no I/O); the ground floor that the
configuration, the supervisor and the drivers read.
"""
