"""The paper's task split and results tables, as the tools set their own numbers beside them."""

from lerobot_jept.envs.metaworld import TABLE7_DEMO_TASKS, TABLE7_UNSEEN_TASKS, TABLE7_VIDEO_TASKS

PAPER_SPLIT = {"demo": TABLE7_DEMO_TASKS, "video": TABLE7_VIDEO_TASKS, "unseen": TABLE7_UNSEEN_TASKS}
# Table 1 (success %), for the paper's own split: rows T_demo, T_vid, the four unseen tasks, seen, unseen average.
TABLE1_ROWS = ["T_demo", "T_vid", *TABLE7_UNSEEN_TASKS, "Seen average", "Unseen average"]
PAPER_TABLE1_ALL = {
    method: dict(zip(TABLE1_ROWS, values, strict=True))
    for method, values in {
        "Vid2Robot-D": [51.8, 4.7, 10.0, 0.0, 4.0, 4.0, 28.2, 4.5],
        "Vid2Robot-M": [46.3, 28.7, 22.0, 4.0, 8.0, 14.0, 37.5, 12.0],
        "BC+IDM": [49.5, 8.3, 8.0, 0.0, 0.0, 4.0, 28.9, 3.0],
        "JEPT+MWM": [44.5, 21.3, 18.0, 4.0, 2.0, 14.0, 32.9, 9.5],
        "DT*": [61.3, 13.0, 6.0, 0.0, 0.0, 0.0, 37.1, 1.5],
        "JEPT": [51.3, 31.7, 28.0, 10.0, 14.0, 22.0, 41.5, 18.5],
    }.items()
}
PAPER_TABLE1 = PAPER_TABLE1_ALL["JEPT"]

# The paper's Table 3 (robosuite), success %; Table 1 lives with the suite.
PAPER_TABLE3 = {
    "Vid2Robot-D": [26.8, 4.0, 4.0, 0.0, 0.0, 0.0, 15.5, 1.0],
    "Vid2Robot-M": [20.7, 11.6, 16.0, 2.0, 4.0, 0.0, 16.1, 5.5],
    "BC+IDM": [26.7, 8.4, 6.0, 0.0, 0.0, 0.0, 17.5, 1.5],
    "JEPT+MWM": [24.3, 10.8, 22.0, 6.0, 2.0, 0.0, 17.6, 7.5],
    "DT*": [36.3, 2.0, 8.0, 0.0, 0.0, 0.0, 19.2, 2.0],
    "JEPT": [27.2, 12.8, 38.0, 16.0, 12.0, 8.0, 20.1, 18.5],
}
TABLE3_ROWS = [
    "T_demo",
    "T_vid",
    "panda-lift",
    "sawyer-lift",
    "iiwa-lift",
    "ur5e-lift",
    "Seen average",
    "Unseen average",
]

# The paper's Table 2 (JEPT, success %) against the number of T_vid tasks in the mixture.
PAPER_TABLE2 = {
    0: {"T_demo": 59.5, "Unseen average": 1.5},
    2: {"T_demo": 49.8, "Unseen average": 1.5},
    4: {"T_demo": 47.0, "Unseen average": 12.5},
    6: {"T_demo": 51.3, "Unseen average": 18.5},
}
