"""The Textual terminal UI: a client of the Supervisor API. The core never imports this."""
