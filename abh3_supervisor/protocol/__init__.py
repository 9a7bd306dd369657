"""Pure ABH3 CAN codec: identifiers, frames, scaling, flag words. No I/O here."""
