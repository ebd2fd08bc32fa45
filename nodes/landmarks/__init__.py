"""Face landmarks: MediaPipe's detector, face mesh and iris model replayed in torch from their
tflite files (`tflite_torch.py`, `network.py`, `iris.py`), which face and following it
(`tracking.py`, numpy; `face_tracker.py`: crops from the previous frame's points), the paper's
heatmap head (`heatmap.py`), the 468 -> 68 correspondence (`correspondence.py`), and the nodes
(`nodes.py`).

Importing the package registers the nodes only; torch and tflite are imported when a node runs.
"""

from .nodes import DetectFaces, FaceLandmarks, LandmarkOverlays, LoadFrames, SaveLandmarks, TrackFaces

__all__ = ["LoadFrames", "DetectFaces", "FaceLandmarks", "TrackFaces", "SaveLandmarks", "LandmarkOverlays"]
