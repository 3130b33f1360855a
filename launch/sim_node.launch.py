"""Start sim_node on a ROS 2 Jazzy machine, with its scalar parameters as launch arguments.

    source /opt/ros/jazzy/setup.bash && source install/setup.bash      (after the colcon build, docs/ros-build.md)
    ros2 launch fluidlab_ros sim_node.launch.py
    ros2 launch fluidlab_ros sim_node.launch.py mode:=robot command_topic:=/my_velocity_controller/commands
    ros2 launch fluidlab_ros sim_node.launch.py params_file:=/path/to/sim_node.yaml
    ros2 launch fluidlab_ros sim_node.launch.py --show-args        (every argument, its default and description)

Each argument in ARGUMENTS sets the sim_node parameter of the same name. Its default is the node's own default
(fluidlab_ros.sim_node.PARAMETERS; tests/ros/test_colcon_build.py checks that the two agree), so a launch without
arguments starts the node as `ros2 run fluidlab_ros sim_node` does. A value is converted to the parameter's type
before it reaches the node: `control_rate:=1000` arrives as 1000.0, booleans are true/false, and `mode:=on` stays
a string.

The two list parameters, controller_joint_names and twin_initial_positions, have no argument of their own: set
them (or any other parameter) in a ROS 2 parameter file given as params_file, e.g.

    sim_node:
      ros__parameters:
        controller_joint_names: [fr3_joint1, fr3_joint2, fr3_joint3, fr3_joint4, fr3_joint5, fr3_joint6, fr3_joint7]

The file is applied after the arguments, so a parameter set in it wins over its argument.
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue

# argument (= parameter) name -> (default as written on the command line, parameter type, description).
# A plain literal, so that the test can read it with ast without importing launch (which has no wheel).
ARGUMENTS = {
    "robot_model": ("fr3", "str", "fr3 or panda (robot_models/)"),
    "mode": ("twin", "str", "twin: no hardware; robot: command the real arm (after ~/arm)"),
    "control_rate": ("500.0", "float", "Hz of the command stream; must divide 1 kHz"),
    "command_topic": ("/fluidlab_velocity_controller/commands", "str",
                      "the JointGroupVelocityController's command topic"),
    "joint_state_topic": ("/franka/joint_states", "str", "measured joint states (robot mode)"),
    "joint_state_qos": ("best_effort", "str", "best_effort or reliable"),
    "joint_state_timeout": ("0.1", "float", "s without a joint state before the motion stops (robot mode)"),
    "late_tick_limit": ("0.02", "float", "s: a control tick later than this stops the motion"),
    "trajectory_folder": ("trajectories", "str",
                          "folder of trajectories (<folder>/<Task>/<name>.json), relative to the working directory"),
    "margin": ("0.8", "float", "fraction of every official limit a plan may use"),
    "max_path_error": ("0.005", "float", "m: refuse a plan whose executed tool path leaves the trajectory's by more"),
    "max_orientation_error": ("0.05", "float", "rad: the same for the tool's orientation"),
    "fluid_twin": ("true", "bool", "simulate the task's fluid with the executed tool motion"),
    "fluid_record_timeout": ("180.0", "float", "s an execution's result waits for the fluid twin"),
    "arch": ("cpu", "str", "Taichi backend of the worker processes (cpu, cuda, auto)"),
    "precision": ("f32", "str", "f32 or f64 in the worker processes"),
    "state_publish_rate": ("50.0", "float", "Hz of the twin joint states and tool pose"),
    "cancel_timeout": ("0.5", "float", "s an optimiser gets to stop after a cancel before it is terminated"),
    "realtime_priority": ("10", "int", "SCHED_FIFO priority of the command-stream process (0: normal scheduling)"),
    "feedback_gain": ("2.0", "float", "1/s: position feedback on the verified profile (0: off)"),
    "feedback_max_velocity": ("0.05", "float", "rad/s: the largest feedback correction"),
    "record": ("true", "bool", "record every execution as rosbag2 MCAP (docs/replay.md)"),
    "recording_folder": ("recordings", "str", "where recordings go, relative to the working directory"),
}

# launch_ros converts a substituted value to this type (ParameterValue(value_type=...)). Without it, launch reads
# every value as YAML: `control_rate:=1000` would reach the node as an integer, which rclpy refuses for a double
# parameter, and `mode:=on` would become a boolean.
TYPES = {"str": str, "float": float, "int": int, "bool": bool}


def _sim_node(context):
    parameters = [{name: ParameterValue(LaunchConfiguration(name), value_type=TYPES[kind])
                   for name, (_, kind, _) in ARGUMENTS.items()}]
    params_file = LaunchConfiguration("params_file").perform(context)
    if params_file:
        parameters.append(params_file)
    return [Node(
        package="fluidlab_ros",
        executable="sim_node",  # lib/fluidlab_ros/sim_node, as `ros2 run fluidlab_ros sim_node`
        name="sim_node",
        output="screen",
        parameters=parameters,
        # Ctrl-C sends SIGINT; sim_node then ramps a running command stream to rest and stops its worker
        # processes. Give it 15 s before launch escalates to SIGTERM (default 5 s).
        sigterm_timeout="15",
    )]


def generate_launch_description():
    declared = [DeclareLaunchArgument(name, default_value=default, description=what)
                for name, (default, _, what) in ARGUMENTS.items()]
    declared.append(DeclareLaunchArgument(
        "params_file", default_value="",
        description="optional ROS 2 parameter file for sim_node (e.g. the list parameters); applied last"))
    return LaunchDescription([*declared, OpaqueFunction(function=_sim_node)])
