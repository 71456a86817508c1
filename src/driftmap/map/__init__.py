"""Maps: world-frame point clouds materialised from stored frames and their poses."""
