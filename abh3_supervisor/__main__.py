"""``python -m abh3_supervisor`` is the ``abh3`` command."""

from abh3_supervisor.clients.cli import run

run()
