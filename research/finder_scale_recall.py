"""Finder recall of MediaPipe's hands on video/wild clips with the frame letterboxed into
larger inputs than the 160 px the finder was trained at (the network is convolutional; its
size output stays in units of 160 input px), and with two sizes merged.

    python research/finder_scale_recall.py train|held [STEP] [THRESHOLD]

Every STEP-th frame (default 3). Per size: recall (a box of IoU > 0.3 with the label's
square), false boxes a frame (IoU < 0.1 with every label), and recall by hand size.
"""
import sys

import numpy as np
import onnx
import onnxruntime as ort

from handmocap.perception import hand_finder as hf
from handmocap.perception.crops import square_box
from handmocap.training import eval_people, real_data
from handmocap.training.pose_data import SHARED_DATA

SIZES = (160, 224, 256, 320)


def dynamic_session(path=hf.DEFAULT_PATH):
    """models/finder.onnx with free input height and width."""
    m = onnx.load(str(path))
    for t, names in ((m.graph.input[0], ("h", "w")), (m.graph.output[0], ("gh", "gw"))):
        d = t.type.tensor_type.shape.dim
        d[2].dim_param, d[3].dim_param = names
    del m.graph.value_info[:]
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    return ort.InferenceSession(m.SerializeToString(), opts, providers=["CPUExecutionProvider"])


def find(session, image, size, threshold):
    """Boxes (k,4) frame px and scores, as HandFinder.find with the frame letterboxed to `size`."""
    boxed, lb = hf.letterbox(image, size)
    maps = session.run(None, {"image": hf.to_input_tensor(boxed[None, ..., ::-1])})[0][0]
    out = hf.decode(maps, threshold, 2)
    return [(lb.to_frame(b.reshape(2, 2)).reshape(4), s) for b, s, _ in out]


def merge(a, b, nms_iou=0.3, k=2):
    boxes = sorted(a + b, key=lambda x: -x[1])
    kept = []
    for box, s in boxes:
        if kept and hf.box_iou(box, np.array([x[0] for x in kept])).max() > nms_iou:
            continue
        kept.append((box, s))
        if len(kept) == k:
            break
    return kept


def main():
    held = sys.argv[1] == "held"
    step = int(sys.argv[2]) if len(sys.argv) > 2 else 3
    thr = float(sys.argv[3]) if len(sys.argv) > 3 else 0.3
    session = dynamic_session()
    keys = [str(s) for s in SIZES] + ["160+256", "160+320"]
    tot = {k: np.zeros(3) for k in keys}          # labels, found, false boxes
    small = {k: np.zeros(2) for k in keys}        # hands under 8% of the frame's long side
    frames = 0
    for video in real_data.wild_clips(SHARED_DATA, held_back=held):
        c = {k: np.zeros(3) for k in keys}
        n = 0
        for f, (img, hands, rel, sides) in enumerate(eval_people.frames_of_clip(video)):
            if f % step:
                continue
            n += 1
            per = {str(s): find(session, img, s, thr) for s in SIZES}
            per["160+256"] = merge(per["160"], per["256"])
            per["160+320"] = merge(per["160"], per["320"])
            labs = [square_box(h) for h in hands]
            for k, found in per.items():
                boxes = [b for b, _ in found]
                for lb in labs:
                    hit = any(hf.box_iou(lb, b)[0, 0] > 0.3 for b in boxes)
                    c[k][0] += 1
                    c[k][1] += hit
                    if (lb[2] - lb[0]) < 0.08 * max(img.shape[:2]):
                        small[k] += (1, hit)
                c[k][2] += sum(not any(hf.box_iou(lb, b)[0, 0] > 0.1 for lb in labs) for b in boxes)
        frames += n
        print(f"{video.stem:40s} " + " ".join(f"{k} {v[1] / max(v[0], 1):.0%}/{v[2] / max(n, 1):.2f}"
                                               for k, v in c.items()), flush=True)
        for k in keys:
            tot[k] += c[k]
    print(f"\n{'size':>8s} {'recall':>7s} {'false/frame':>11s} {'small-hand recall':>18s}  ({frames} frames)")
    for k in keys:
        print(f"{k:>8s} {tot[k][1] / tot[k][0]:7.3f} {tot[k][2] / frames:11.3f} "
              f"{small[k][1] / max(small[k][0], 1):9.3f} of {small[k][0]:.0f}")


if __name__ == "__main__":
    main()
