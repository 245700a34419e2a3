"""lifemap: a Python client for lifemapd (lifelong RGB-D maps of indoor places).

    import lifemap
    with lifemap.Client("127.0.0.1:50051", api_key=KEY) as client:
        client.create_map("lab")
        for result in client.stream("lab", frames, intrinsics=(525, 525, 319.5, 239.5)):
            print(result.sequence, result.keyframe_id, result.entropy_mask.mean())

See client/python/README.md; the messages are lifemap.v1.* (generated from proto/).
"""
from lifemap.client import Client, Error, Frame, FrameResult

__all__ = ["Client", "Error", "Frame", "FrameResult"]
