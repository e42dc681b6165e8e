"""Shots found while authoring the suite: θ and the task plan its MuJoCo C replay decodes to.

For each scene, three uniform shots (seed 7) from different task plans, rounded
to 1 mm or 1 mm/s (or 1 mN·m) and kept only where the rounded shot and four
perturbations of up to 1e-3 decode to the same successful plan. They show
each scene has the modes its header describes; tests/test_scene_suite.py
replays them. θ is in the order of the task"s variables (see tasks.py).
"""

EXAMPLES: dict[str, list[tuple[list[float], str]]] = {
    "rolling_ball": [
        ([2.029, -2.095], "00010-south"),
        ([2.163, 2.981], "00100-north"),
        ([1.956, -0.233], "00000-south"),
    ],
    "pachinko": [
        ([0.119, -0.064], "000000-bin3"),
        ([-0.098, -0.11], "000100-bin2"),
        ([0.002, 0.107], "101010-bin3"),
    ],
    "arm_strike": [
        ([0.903, 0.898, -0.75, -0.697, -0.185, 0.668], "0010-west"),
        ([-0.611, -0.291, 0.798, 0.973, -0.114, 0.552], "0100-east"),
        ([-0.548, -0.263, 0.558, 0.867, -0.692, -0.94], "0000-east"),
    ],
    "pendulum_bells": [
        ([0.751, 2.383, 1.654, -1.649, -1.199, 2.241], "0100-right"),
        ([-2.968, 1.927, 1.782, -0.192, -1.182, -1.329], "1000-left"),
        ([-2.969, 1.518, 1.863, -2.179, -0.487, 1.892], "1100-right"),
    ],
    "pusher": [
        ([-0.227, 0.227, 0.221, -0.18], "00-south"),
        ([0.207, 0.052, 0.539, -0.414], "10-south"),
        ([-0.122, -0.041, 0.375, 0.187], "00-north"),
    ],
    "bank_shot": [
        ([3.251, -1.846], "0100-top"),
        ([2.883, 0.636], "0000-top"),
        ([3.435, 0.959], "0000-right"),
    ],
    "wedges": [
        ([2.872, 0.54], "00001-north"),
        ([1.457, 0.484], "00101-north"),
        ([1.328, -0.331], "00001-south"),
    ],
    "crate_ledge": [
        ([0.304, 0.016, 0.312, -0.291], "100-east"),
        ([-0.115, -0.139, 0.017, 0.144], "000-north"),
        ([0.467, 0.27, -0.12, -0.129], "011-south"),
    ],
    "cans": [
        ([0.143, -0.015], "0-a_north"),
        ([0.092, -0.144], "0-b_south"),
        ([0.127, 0.151], "1-a_north+b_north"),
    ],
}
