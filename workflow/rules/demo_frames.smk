# Demo frames (issue 9): perspective drone views of the demo city with known poses, rendered by
# georeg.demo.frames from scene.json (another sun, camera response, noise, lens distortion).

DEMO_FRAME_VIEWS = (config.get("frame_loc") or {}).get("demo_frames") or {}


rule demo_frames:
    input:
        scene="results/demo/scene.json",
    output:
        frames=expand(
            "results/demo/frames/{view}.png",
            view=[v["name"] for v in DEMO_FRAME_VIEWS.get("views") or []],
        ),
        truth="results/demo/frames/truth.json",
    params:
        demo_frames=DEMO_FRAME_VIEWS,
    log:
        "logs/demo/demo_frames.log",
    benchmark:
        "benchmarks/demo/demo_frames.tsv"
    threads: 1
    script:
        "../../scripts/demo_frames.py"


# Demo video (issue 10): a smooth drone flight over the demo city with a truth pose per frame,
# rendered by georeg.demo.video from the same textured scene as the frames above.

rule demo_video:
    input:
        scene="results/demo/scene.json",
    output:
        video="results/demo/video/flight.mp4",
        truth="results/demo/video/truth.json",
    params:
        demo_video=(config.get("trajectory") or {}).get("demo_video") or {},
    log:
        "logs/demo/demo_video.log",
    benchmark:
        "benchmarks/demo/demo_video.tsv"
    priority: 30
    threads: 1
    script:
        "../../scripts/demo_video.py"
