"""Generated: proto package ``tamrm.v1``."""
