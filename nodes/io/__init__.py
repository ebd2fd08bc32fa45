"""Reading and writing mesh, image, video, rigid and parameter sequences, and face models."""

from .._areas import import_modules

import_modules(__name__, ["mesh", "image", "video", "sequences", "face_model", "stabilization",
                          "camera", "livelink"])
