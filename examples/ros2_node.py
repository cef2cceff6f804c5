"""A ROS 2 node: depth camera in, elevation map out as grid_map_msgs/GridMap (and foxglove_msgs/Grid bytes).

NEEDS ROS 2 (rclpy, tf2_ros, sensor_msgs, grid_map_msgs; Humble or later) and is NOT run by the tests:
elevmap itself never needs ROS. Run it in a sourced ROS 2 environment where elevmap is installed:

    python examples/ros2_node.py --ros-args -p depth_topic:=/camera/depth/image_rect_raw \\
        -p info_topic:=/camera/depth/camera_info -p map_frame:=odom

Each depth image (16UC1/mono16 millimetres, or 32FC1 metres; for image_transport's compressedDepth subscribe
to ``.../compressedDepth`` with ``sensor_msgs/CompressedImage`` and use ``compressed_depth_to_depth``) is
fused at the pose tf2 gives for its stamp; the map follows the camera and is published at ``rate`` Hz.
The conversions are ``elevmap.ros``'s: they read rclpy messages as they read those of a bag.
"""

from __future__ import annotations

import array

import rclpy
from grid_map_msgs.msg import GridMap
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.time import Time
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Float32MultiArray, MultiArrayDimension
from tf2_ros import Buffer, TransformException, TransformListener

from elevmap import Camera, ElevationMap, Mapper
from elevmap.ros import BAG_LAYERS, camera_info_to_K, image_to_depth, stamp_seconds, transform_to_matrix


class ElevationMapNode(Node):
    def __init__(self):
        super().__init__("elevmap")
        self.depth_topic = self.declare_parameter("depth_topic", "/camera/depth/image_rect_raw").value
        self.map_frame = self.declare_parameter("map_frame", "odom").value
        info_topic = self.declare_parameter("info_topic", "/camera/depth/camera_info").value
        rate = self.declare_parameter("rate", 2.0).value
        self.emap = ElevationMap(8.0, 0.04)
        self.mapper = Mapper(self.emap)
        self.tf = Buffer()
        self.tf_listener = TransformListener(self.tf, self)
        self.create_subscription(CameraInfo, info_topic, self.on_info, 1)
        self.create_subscription(Image, self.depth_topic, self.on_depth, 5)
        self.publisher = self.create_publisher(GridMap, "elevation_map", 1)
        self.create_timer(1.0 / rate, self.publish)

    def on_info(self, msg: CameraInfo):
        if self.depth_topic not in self.mapper.cameras:
            K, width, height = camera_info_to_K(msg)
            self.mapper.add_camera(Camera(self.depth_topic, K, width, height, depth_scale=0.001))

    def on_depth(self, msg: Image):
        if self.depth_topic not in self.mapper.cameras:
            return                                           # no camera info yet
        try:
            t = self.tf.lookup_transform(self.map_frame, msg.header.frame_id, Time.from_msg(msg.header.stamp),
                                         timeout=Duration(seconds=0.05))
        except TransformException as exc:
            self.get_logger().warn(f"frame skipped, no transform: {exc}")
            return
        T_map_cam = transform_to_matrix(t.transform)
        self.emap.move_to(T_map_cam[:2, 3])
        self.mapper.integrate(self.depth_topic, image_to_depth(msg), T_map_cam=T_map_cam,
                              stamp=stamp_seconds(msg.header.stamp))

    def publish(self):
        g = self.emap.to_grid_map(BAG_LAYERS, frame_id=self.map_frame)
        m = GridMap()
        m.header.frame_id = g["frame_id"]
        m.header.stamp = self.get_clock().now().to_msg()
        m.info.resolution, m.info.length_x, m.info.length_y = g["resolution"], g["length_x"], g["length_y"]
        m.info.pose.position.x, m.info.pose.position.y = g["position"]
        m.info.pose.orientation.w = 1.0
        m.layers, m.basic_layers = g["layers"], g["basic_layers"]
        dims = [MultiArrayDimension(label=d["label"], size=d["size"], stride=d["stride"]) for d in g["layout"]]
        for name in g["layers"]:
            layer = Float32MultiArray()
            layer.layout.dim = dims
            layer.data = array.array("f", g["data"][name].tobytes())
            m.data.append(layer)
        self.publisher.publish(m)


def main():
    rclpy.init()
    node = ElevationMapNode()
    try:
        rclpy.spin(node)
    finally:
        node.destroy_node()
        rclpy.shutdown()


if __name__ == "__main__":
    main()
