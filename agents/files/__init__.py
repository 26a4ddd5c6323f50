"""What goes to and comes from disk: CARMEN logs (:mod:`~agents.files.carmen`), ROS bags
(:mod:`~agents.files.rosbag`), map exports
(:mod:`~agents.files.export`), pictures (:mod:`~agents.files.render`), Rerun recordings
(:mod:`~agents.files.rerun_log`) and atomic file helpers (:mod:`~agents.files.io`)."""
