"""Generated: proto package ``tamrm``."""
