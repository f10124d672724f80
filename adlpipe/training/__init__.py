"""Training a policy: the loop every model shares (loop), what it reads (data) and what it measures (validation)."""
