"""Sans-I/O codecs, one module per wire protocol: bytes in, events out.

Nothing here reads a port, sleeps, or imports the rest of m2s2hil.
"""
