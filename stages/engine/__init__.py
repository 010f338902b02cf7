"""Scale-out: the Ray worker pool and the chunked render jobs."""
