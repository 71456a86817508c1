"""Registration: KISS-ICP odometry, pairwise GICP verification, loop-closure candidates."""
