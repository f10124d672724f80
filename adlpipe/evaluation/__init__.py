"""What scores a policy and what the scores mean: the scenes it is replayed in (recorded or fresh)."""
