"""Scale-out: the Ray worker pool (pool), the chunked render jobs and their workers (chunks), and the
attack and guidance workers (attack_worker, guidance_worker), each with its frozen setup and job records."""
