"""handmocap's interop wing: the graph's messages to and from other systems (Foxglove, ROS 2,
bag files on the command line). It may import the runtime (bus, codec, bags) and the
perception (geometry, the hand model); neither imports it."""
