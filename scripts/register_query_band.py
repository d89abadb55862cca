"""Rule query_band: select, mask and stretch the query band and the bands pooled with it
(band.tif, the primary band first, + band.json)."""

from georeg.io.scripting import run
from georeg.register.band import write_query_band


def main(smk):
    q = smk.params.query
    write_query_band(
        q["image"],
        q.get("band", "1200nm"),
        q.get("gsd_m"),
        smk.output.band,
        smk.output.meta,
        tuple(smk.params.percentiles),
        q.get("bands", "auto"),
        q.get("prior"),
    )


run(snakemake, main)  # noqa: F821
