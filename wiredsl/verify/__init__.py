"""Images in: where the camera was for each (board.py), and what a detector finds against the scene."""
