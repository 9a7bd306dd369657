"""Front ends: the command line, the terminal UI, the control-socket client, ``abh3 decode``."""
