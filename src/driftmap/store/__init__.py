"""Frame store and pose ledger."""

from driftmap.store.guards import atomic_output, is_store_folder, refuse_inside_store, store_folder_of

__all__ = ["atomic_output", "is_store_folder", "refuse_inside_store", "store_folder_of"]
