#!/usr/bin/env bash
# The device checks of issues 23 and 48 as one prepared run on a CUDA machine (see
# benchmarks/device.py and docs/benchmarks.md, "GPU end to end"). Here, where open3d and
# ../shared are: `python benchmarks/device.py --make-inputs gpu_inputs/`; there:
#   bash benchmarks/device_check.sh gpu_inputs/ OUT/
# The machine needs torch with CUDA, opencv, scipy, tqdm, pyyaml and pytest; open3d,
# trimesh and rerun may be missing (a stand-in takes fusion's place). Writes OUT/log.txt,
# OUT/{agreement,speed,speed_suspects,profile}.json and OUT/fused/ (bring them back; then, where open3d
# is: `python benchmarks/device.py --inputs gpu_inputs/ --compare OUT/fused/fused-cpu
# OUT/fused/fused-cuda` scores both runs' meshes). About 6 minutes on an H200.
set -o pipefail
inputs="${1:?usage: device_check.sh INPUTS OUT}"
out="${2:?usage: device_check.sh INPUTS OUT}"
mkdir -p "$out"
inputs="$(cd "$inputs" && pwd)" out="$(cd "$out" && pwd)"  # before moving to the repository's root
export PYTHONUNBUFFERED=1
cd "$(dirname "$0")/.."
{
    date -u
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
    python3 -c "import torch, cv2; print('torch', torch.__version__, 'cv2', cv2.__version__, 'cuda', torch.cuda.is_available())"
    echo "== the device-parametrised tests on cuda"
    timeout 120 python3 -m pytest -q -k cuda -p no:cacheprovider tests/test_medea_core.py tests/test_mvs_core.py \
        tests/test_pipeline_devices.py 2>&1 | tail -8
    echo "== agreement (7-Scenes, CUDA then CPU)"
    timeout 200 python3 benchmarks/device.py --inputs "$inputs" --devices cuda cpu --parts agreement \
        --save-depth "$out/fused" --json "$out/agreement.json"
    echo "== speed (the 300-frame video at the defaults)"
    timeout 240 python3 benchmarks/device.py --inputs "$inputs" --devices cuda --parts speed --json "$out/speed.json"
    # Two suspects of stop 62 at once: the front end on torch's 16 threads (the estimated
    # row's pose stage) and the prior given 1-8 frames a call (the given row's prior stage).
    echo "== speed with the front end on 2 torch threads and the prior's batches padded"
    timeout 150 python3 benchmarks/device.py --inputs "$inputs" --devices cuda --parts speed --pose-threads 2 \
        --prior-fixed-batch --json "$out/speed_suspects.json"
    echo "== profile (the front end)"
    timeout 100 python3 benchmarks/device.py --inputs "$inputs" --devices cuda --parts profile --json "$out/profile.json"
    date -u
} 2>&1 | tee "$out/log.txt"
