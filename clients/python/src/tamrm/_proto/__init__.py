"""Generated protobuf messages of tamrm (scripts/gen_protos.py)."""
