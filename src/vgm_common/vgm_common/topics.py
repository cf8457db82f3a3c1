"""Every topic name and frame of the graph's public contract (docs/INTERFACES.md,
"Topics" and "Frames"), in one place; the QoS profiles are in ``vgm_common.qos``."""

# --- frames ----------------------------------------------------------------------------
BASE_FRAME = 'base_link'
TOOL_FRAME = 'tool0'
CAMERA_NAMES = ('left', 'right', 'aux')
OPTICAL_FRAMES = {
    'left': 'stereo_left_optical_frame',
    'right': 'stereo_right_optical_frame',
    'aux': 'aux_optical_frame',
}

# --- cameras (sensor_sim, calib_node) --------------------------------------------------
_CAMERA_NAMESPACES = {'left': '/stereo/left', 'right': '/stereo/right', 'aux': '/aux'}
IMAGE_TOPICS = {name: f'{ns}/image_raw' for name, ns in _CAMERA_NAMESPACES.items()}
CAMERA_INFO_TOPICS = {name: f'{ns}/camera_info' for name, ns in _CAMERA_NAMESPACES.items()}
POSE_TOPICS = {name: f'{ns}/pose' for name, ns in _CAMERA_NAMESPACES.items()}
TARGET_POSE_TOPIC = '/calibration/target_pose'

# --- curve_recon_node ------------------------------------------------------------------
WAYPOINTS_TOPIC = '/curve/waypoints'
CURVE_POINTS_TOPIC = '/curve/points'

# --- sfs_stereo_node -------------------------------------------------------------------
DISPARITY_TOPIC = '/stereo/disparity'
STEREO_DEPTH_TOPIC = '/depth/stereo'
SFS_DEPTH_TOPIC = '/depth/sfs'
FUSED_DEPTH_TOPIC = '/depth/fused'
DEPTH_INFO_TOPIC = '/depth/camera_info'
DEPTH_CONFIDENCE_TOPIC = '/depth/confidence'
DEPTH_POINTS_TOPIC = '/depth/points'
LEFT_RECT_TOPIC = '/stereo/left/image_rect'

# --- stereo_coding_node, stereo_decoding_node -----------------------------------------
CODED_IMAGE_TOPIC = '/stereo/coded/image'
CODED_COMPRESSED_TOPIC = '/stereo/coded/image/compressed'
DECODED_DISPARITY_TOPIC = '/stereo/decoded/disparity'
DECODED_LEFT_TOPIC = '/stereo/decoded/left/image_rect'
DECODED_RIGHT_TOPIC = '/stereo/decoded/right/image_rect'

# --- live_view: Foxglove FrameTransforms (tf2_msgs is not in the wheels) -----------------
TRANSFORMS_TOPIC = '/tf'

# --- the arm (sensor_sim, pa10_ik_node) ------------------------------------------------
PRESSURE_TOPIC = '/tool/pressure'
JOINT_STATES_TOPIC = '/joint_states'
JOINT_TRAJECTORY_TOPIC = '/pa10_controller/joint_trajectory'
TOOL_POSE_TOPIC = '/tool_pose'

DIAGNOSTICS_TOPIC = '/diagnostics'
