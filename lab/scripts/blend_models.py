# Weight-space blend of two adapted models (same architecture): out = lam*b + (1-lam)*a, every
# float tensor (BatchNorm running statistics and vertex features included). Replay measurement
# for issue 19; the manifest's file hashes are rewritten.
import hashlib, json, os, sys
from safetensors.numpy import load_file, save_file
a, b, lam, out = sys.argv[1], sys.argv[2], float(sys.argv[3]), sys.argv[4]
os.makedirs(out)
m = json.load(open(f"{a}/manifest.json"))
for f in m["files"] if isinstance(m["files"], list) else m["files"].keys():
    ta, tb = load_file(f"{a}/{f}"), load_file(f"{b}/{f}")
    blended = {k: (lam * tb[k] + (1 - lam) * v).astype(v.dtype) if v.dtype.kind == "f" else v for k, v in ta.items()}
    save_file(blended, f"{out}/{f}")
m["version"] = os.path.basename(out)
if isinstance(m["files"], dict):
    m["files"] = {f: hashlib.sha256(open(f"{out}/{f}", "rb").read()).hexdigest() for f in m["files"]}
json.dump(m, open(f"{out}/manifest.json", "w"), indent=2)
