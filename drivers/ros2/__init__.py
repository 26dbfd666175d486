"""ROS 2 over DDS without a ROS install: the transport (:mod:`drivers.ros2.dds`) and the
input drivers reading ROS 2 topics (:mod:`drivers.ros2.inputs`)."""
