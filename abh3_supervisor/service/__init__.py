"""The supervisor as a service: a local control endpoint and the clients that use it."""
