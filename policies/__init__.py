"""External controllers for trajeglish_env agents (builds on trajeglish_env; never imported by it)."""
