"""Wire contract with the drive firmware and the PLC: frame layouts, register maps, scaling, CRC.

Imports nothing from ``agent`` or ``protocols``; both import from here. Exports a C header and a
DBC so firmware uses the same definitions.
"""
