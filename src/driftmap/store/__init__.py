"""Frame store and pose ledger."""
