"""Datasets and bags (no rclpy): the dataset format, bag I/O, the bag-to-dataset builder."""

from softshape_ros.data.dataset import (  # noqa: F401
    ContactRecord, Dataset, DatasetError, DatasetWriter, load_dataset, write_dataset)
