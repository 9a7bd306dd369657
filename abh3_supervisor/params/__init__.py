"""Drive parameters: the TelABH3 codec, the J1939 transport, the address table, sessions.

Sans-I/O like ``protocol/``: imports nothing of ours but ``protocol`` and ``errors``.
"""
