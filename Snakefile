# georeg: register airborne imagery to a geo-referenced map without GPS.
# Table of contents only; each stage lives in workflow/rules/<stage>.smk.
# Rule priorities order ready jobs on few cores: the demo video first (30, the longest job), the
# query chain (20), the map tiles and index (10), frames last (0); measured in docs/BENCHMARKS.md.
import os

from snakemake.utils import min_version

min_version("9.0")


configfile: os.path.join(workflow.basedir, "config", "config.yaml")


report: "workflow/report/workflow.rst"


include: "workflow/rules/common.smk"


wildcard_constraints:
    name=query_name_pattern(),


include: "workflow/rules/demo.smk"
include: "workflow/rules/map.smk"
include: "workflow/rules/index.smk"
include: "workflow/rules/register.smk"
include: "workflow/rules/products.smk"
include: "workflow/rules/report.smk"
include: "workflow/rules/demo_frames.smk"
include: "workflow/rules/frames.smk"
include: "workflow/rules/trajectory.smk"
include: "workflow/rules/export.smk"


rule all:
    input:
        all_inputs,
    default_target: True
