"""Generated grpcio service stubs of the tamrm API, for the tests only (scripts/gen_protos.py)."""
