"""A ROS 2 camera made of a video file: sensor_msgs/Image (bgr8) and CameraInfo at the
clip's rate, as a camera driver publishes them; plain rclpy, no handmocap import. With the
graph's ros2 launch file it stands in for a robot's camera:
    handlaunch launch/ros2.yaml &
    python examples/ros2_publish_video.py data/demo/hand_clip.mp4   # -> /camera/image_raw, /camera/camera_info
Options: --topic, --fps, --frames N (the first N), --best-effort (sensor-data QoS; default
reliable, as many drivers publish), --compressed (sensor_msgs/CompressedImage, JPEG, on
TOPIC/compressed, as image_transport names it), --stamps FILE (each frame's stamp, a line each).
It waits (up to --wait s) for a subscriber before the first frame.
"""
import argparse
import math
import os
import sys
import time

import cv2

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
import rclpy                                                            # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data   # noqa: E402
from sensor_msgs.msg import CameraInfo, CompressedImage, Image         # noqa: E402


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("video")
    p.add_argument("--topic", default="/camera/image_raw")
    p.add_argument("--fps", type=float, default=None, help="default: the clip's")
    p.add_argument("--frames", type=int, default=None)
    p.add_argument("--best-effort", action="store_true")
    p.add_argument("--compressed", action="store_true")
    p.add_argument("--wait", type=float, default=30.0)
    p.add_argument("--stamps", default=None)
    args = p.parse_args()
    cap = cv2.VideoCapture(args.video)
    if not cap.isOpened():
        sys.exit(f"{args.video}: can't be opened")
    fps = args.fps or cap.get(cv2.CAP_PROP_FPS) or 30.0
    rclpy.init()
    node = rclpy.create_node("video_camera")
    qos = qos_profile_sensor_data if args.best_effort else QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    image_pub = node.create_publisher(CompressedImage if args.compressed else Image,
                                      args.topic + "/compressed" if args.compressed else args.topic, qos)
    info_pub = node.create_publisher(CameraInfo, args.topic.rsplit("/", 1)[0] + "/camera_info", qos)
    deadline = time.monotonic() + args.wait
    while image_pub.get_subscription_count() == 0 and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.05)
    stamps = open(args.stamps, "w") if args.stamps else None
    sent, next_due = 0, time.monotonic()
    while args.frames is None or sent < args.frames:
        ok, frame = cap.read()
        if not ok:
            break
        time.sleep(max(0.0, next_due - time.monotonic()))
        next_due += 1.0 / fps
        h, w = frame.shape[:2]
        now = node.get_clock().now().to_msg()
        if args.compressed:
            image = CompressedImage(format="jpeg", data=cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes())
        else:
            image = Image(height=h, width=w, encoding="bgr8", is_bigendian=0, step=w * 3, data=frame.tobytes())
        image.header.stamp, image.header.frame_id = now, "camera_optical_frame"
        f = (w / 2) / math.tan(math.radians(30))                  # a 60 degree horizontal field of view
        info = CameraInfo(height=h, width=w, distortion_model="plumb_bob", d=[0.0] * 5,
                          k=[f, 0.0, (w - 1) / 2, 0.0, f, (h - 1) / 2, 0.0, 0.0, 1.0])
        info.header = image.header
        info_pub.publish(info)
        image_pub.publish(image)
        sent += 1
        if stamps:
            stamps.write(f"{now.sec * 1_000_000_000 + now.nanosec}\n")
    if stamps:
        stamps.close()
    time.sleep(0.5)                                               # let a reliable reader take the last frames
    print(f"sent {sent} frames to {args.topic}", file=sys.stderr, flush=True)
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == "__main__":
    main()
