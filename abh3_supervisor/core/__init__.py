"""The supervisor's domain: units, commands, arbitration of input sources, kinematics.

No I/O, no threads, no UI and no plugin dependency: everything here is driven by the
scheduler and the runtime, and is tested with a fake clock.
"""
