"""``abh3 commission``: a guided, interruptible bring-up of a unit's drive, and its report.

Sans-I/O like the core: :mod:`.analysis` judges sample series (pure), :mod:`.guard`
watches a moving unit on the supervisor's events, :mod:`.sequence` runs the steps (those
that move nothing in :mod:`.identity`) against a :class:`~.unit.Bench` (time, motion
through the input arbitration, parameter reads) and an :class:`~.unit.Operator`
(questions, the e-stop key), which the terminal client (clients/commission.py) or a
fake-clock test provides; :mod:`.report` renders the result as JSON and as a
self-contained HTML page with inline SVG plots (:mod:`.svg`).
"""
