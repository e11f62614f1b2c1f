"""The web viewer (`uw-viewer RUN/config.yml`, `uw-train ... --viewer`), built on viser.

- `camera`: viser's camera (position, wxyz, vertical fov, aspect) <-> this project's `Camera` (OpenCV, world-to-camera);
- `render`: one view of a model as an 8-bit image, with the water control (betas scaled by k, B_inf replaced);
- `server`: the viser server, its GUI, the training and test camera frustums, and when to render for which client.
"""
