"""Recording I/O: cameras and their presets, depth and colour images, recording folders
(:mod:`tracker.io.recording`, the API in one import) and the files read in place (ROS and RealSense
bags, Azure Kinect ``.mkv``). The tracking stages never import the files' readers; they take frames.
``tracker.live`` (a live camera) stays beside the stages."""
