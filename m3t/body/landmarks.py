"""MediaPipe's landmark names in its index order: the point vocabulary of every body model's MediaPipe-Holistic
correspondence (``"pose:<name>"``, ``"left_hand:<name>"``), of the skeleton graphs and of ``.pose`` files
(which spell them upper-case).
"""
from __future__ import annotations

# mediapipe/python/solutions/pose.py PoseLandmark ("pose_landmark" model card: 33 landmarks). Indices 0-16 are
# the head and arms; 17-22 are the coarse hand points (pinky, index, thumb) the hand models replace; 23-32 the
# hips and legs.
POSE_LANDMARKS = (
    "nose", "left_eye_inner", "left_eye", "left_eye_outer", "right_eye_inner", "right_eye", "right_eye_outer",
    "left_ear", "right_ear", "mouth_left", "mouth_right", "left_shoulder", "right_shoulder", "left_elbow",
    "right_elbow", "left_wrist", "right_wrist", "left_pinky", "right_pinky", "left_index", "right_index",
    "left_thumb", "right_thumb", "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle",
    "left_heel", "right_heel", "left_foot_index", "right_foot_index",
)

# mediapipe/python/solutions/hands.py HandLandmark ("hand_landmark": 21 points): 0 wrist; 1-4 thumb CMC, MCP,
# IP, tip; 5-8 index MCP, PIP, DIP, tip; 9-12 middle; 13-16 ring; 17-20 pinky. This is also OpenPose's hand order.
HAND_LANDMARKS = (
    "wrist", "thumb_cmc", "thumb_mcp", "thumb_ip", "thumb_tip",
    "index_finger_mcp", "index_finger_pip", "index_finger_dip", "index_finger_tip",
    "middle_finger_mcp", "middle_finger_pip", "middle_finger_dip", "middle_finger_tip",
    "ring_finger_mcp", "ring_finger_pip", "ring_finger_dip", "ring_finger_tip",
    "pinky_mcp", "pinky_pip", "pinky_dip", "pinky_tip",
)
