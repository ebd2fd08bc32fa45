"""Face landmarks: MediaPipe's detector and face mesh replayed in torch from their tflite files
(`tflite_torch.py`, `network.py`), the paper's heatmap head (`heatmap.py`), the 468 -> 68
correspondence (`correspondence.py`), and the nodes (`nodes.py`).

Importing the package registers the nodes only; torch and tflite are imported when a node runs.
"""

from .nodes import DetectFaces, FaceLandmarks, LandmarkOverlays, LoadFrames, SaveLandmarks

__all__ = ["LoadFrames", "DetectFaces", "FaceLandmarks", "SaveLandmarks", "LandmarkOverlays"]
