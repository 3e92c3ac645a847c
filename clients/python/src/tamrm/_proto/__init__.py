"""Generated gRPC stubs of the tamrm API (scripts/gen_protos.py)."""
