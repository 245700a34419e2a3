"""Generated lifemap.v1 Protobuf messages and gRPC stubs (built from proto/ by setup.py)."""
