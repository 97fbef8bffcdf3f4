"""`knotlab serve`: the HTTP decision service (API, request models, worker pool)."""
