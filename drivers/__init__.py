"""Hardware drivers: bytes and frames in, typed robotd messages out."""
