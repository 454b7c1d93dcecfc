"""Print the hands of /hand/pose as they come: pyzmq + msgpack + numpy, no handmocap import.
    python examples/subscribe_pose.py                        # the `ik` node of the graph on this host
    python examples/subscribe_pose.py tcp://10.0.0.2:5560    # an endpoint given by `bind:` in a launch file
"""
import json, os, stat, sys, tempfile
import msgpack, numpy as np, zmq

# Each node says where it publishes in <run dir>/<node>.json (run dir as handmocap.runtime.bus.run_dir).
run_dir = os.environ.get("HANDMOCAP_RUN_DIR") or os.path.join(
    tempfile.gettempdir(), f"handmocap-{os.getuid()}", os.environ.get("HANDMOCAP_GRAPH", "default"))
for d in (run_dir, os.path.dirname(run_dir)) if not os.environ.get("HANDMOCAP_RUN_DIR") else (run_dir,):
    st = os.lstat(d) if os.path.lexists(d) else None         # trust only a private folder of ours, as
    if st and (stat.S_ISLNK(st.st_mode) or st.st_uid != os.getuid() or st.st_mode & 0o077):   # handlaunch does
        sys.exit(f"{d} is not your private folder (uid {st.st_uid}, mode {st.st_mode & 0o777:o}): not reading it")
info = os.path.join(run_dir, "ik.json")
if len(sys.argv) < 2 and not os.path.exists(info):
    sys.exit(f"no ik node runs in {run_dir}: start a graph (handlaunch launch/demo.yaml) or give an endpoint")
endpoint = sys.argv[1] if len(sys.argv) > 1 else json.load(open(info))["endpoint"]
sock = zmq.Context().socket(zmq.SUB)
sock.connect(endpoint)
sock.subscribe(b"/hand/pose\0")                 # frames: [topic + NUL, type name, msgpack payload]


def array(a):                                   # arrays travel as {dtype, shape, data: bytes}
    return np.frombuffer(a["data"], a["dtype"]).reshape(a["shape"])


while (frames := sock.recv_multipart())[1] != b"_eos":                        # _eos: the stream ended
    msg = msgpack.unpackb(frames[2])
    for hand in msg["hands"]:
        xyz, quat = array(hand["xyz"]), array(hand["quat"])   # (21,3) m camera frame; (21,4) w,x,y,z
        # quat[0]: the wrist (whole hand); quat[j]: the bone parent(j) -> j, e.g. 6: index MCP -> PIP
        print(msg["header"]["stamp_ns"], hand["handedness"], "wrist_m", np.round(xyz[0], 3),
              "q_wrist", np.round(quat[0], 3), "q_index_proximal", np.round(quat[6], 3), flush=True)
