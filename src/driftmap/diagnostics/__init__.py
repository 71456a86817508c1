"""Map-consistency diagnostics (double walls, smearing, drift attribution)."""
