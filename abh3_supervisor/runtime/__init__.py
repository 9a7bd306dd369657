"""Running the core: buses, pumps, the stop path, the headless loop and recordings."""
