"""Simulated devices that speak the rig's real wire protocols.

Importing this package registers the ``sim://NAME`` scheme with pyserial.
"""

import serial

if "m2s2hil.simulators" not in serial.protocol_handler_packages:
    serial.protocol_handler_packages.append("m2s2hil.simulators")
