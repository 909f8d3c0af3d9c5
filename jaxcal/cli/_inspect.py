"""`jaxcal inspect DATASET|BAG`: what a capture holds, in seconds (jaxcal.inspection)."""

import dataclasses
import json
import sys

from ..errors import DatasetError
from ..fleet import fleet_datasets, is_fleet
from ..io._files import check_output_file, write_text_atomic
from ._common import count
from ._rosbag import add_bag_args, dataset_of


def add_inspect_parser(sub) -> None:
    p = sub.add_parser("inspect", help="what a dataset or ROS bag holds: cameras, sweeps, clocks, detections")
    p.add_argument("dataset", help="dataset directory or ROS bag (a bag without --images etc.: its topics)")
    p.add_argument(
        "--sample", type=count(1, 1000), default=5, help="frames per camera tried for detection, at most 1000"
    )
    p.add_argument("--json", help="write the summary as JSON here (atomically; - prints it)")
    add_bag_args(p, required=False)
    p.set_defaults(func=cmd_inspect)


def cmd_inspect(args) -> int:
    if args.json not in (None, "-"):
        check_output_file(args.json, inputs=[args.dataset], overwrite=True, what="--json")
    print(f"inspecting {args.dataset} ...", file=sys.stderr, flush=True)
    from ..inspection import format_inspection, inspect_dataset  # JAX (the robot model): after the first line
    from ..io.rosbag import bag_topics, is_bag, open_bag
    from ..records import plain

    if is_fleet([args.dataset]):
        raise DatasetError(
            f"{args.dataset}: a folder of datasets (a fleet; `jaxcal calibrate` takes it whole), not one dataset: "
            f"inspect each, e.g. jaxcal inspect {fleet_datasets([args.dataset])[0]}"
        )
    if is_bag(args.dataset):
        with open_bag(args.dataset) as reader:
            topics = bag_topics(reader)
        print(f"{args.dataset}: ROS bag, topics:")
        for topic, (msgtype, count) in sorted(topics.items()):
            print(f"  {topic}  {msgtype}  ({count} messages)")
        if not (args.images and args.joints and args.robot and args.target):
            print("give --images, --joints, --robot and --target (and --camera-info) to inspect its capture")
            return 0
    with dataset_of(args) as dataset:
        summary = inspect_dataset(dataset, sample=args.sample)
    summary = dataclasses.replace(summary, dataset=str(args.dataset))  # the bag, not its temporary dataset
    if args.json is None:
        print(format_inspection(summary))
    elif args.json == "-":
        print(json.dumps(plain(summary), indent=1))
    else:
        write_text_atomic(args.json, json.dumps(plain(summary), indent=1))
        print(f"wrote {args.json}")
    return 0
