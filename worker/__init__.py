"""RQ workers that run the fitting engine on jobs from Redis."""
