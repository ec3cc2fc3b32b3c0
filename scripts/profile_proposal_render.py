"""Where a proposal preset's evaluation render spends its time: the proposal sampling against the field and compositing,
for one chunk of rays of an untrained nerfacto_forward_cpu model in fern's NDC (the split, not absolute figures).

    .venv/bin/python scripts/profile_proposal_render.py 8192
"""
import sys
import time, torch
from hydra.utils import instantiate
from nerf_lightning.config import compose_config
from nerf_lightning.geometry.space import SceneSpace, NDC
cfg = compose_config(["experiment=nerfacto_forward_cpu", "data.root=unused", "paths.output_dir=/tmp/profile_proposal_render"])  # reads no data
model = instantiate(cfg.model).eval()
model.space = SceneSpace(0.0, 1.0, ndc=NDC(815.0, 1008, 756))
torch.manual_seed(0)
n = int(sys.argv[1]) if len(sys.argv) > 1 else 8192
o = torch.randn(n, 3) * 0.1
d = torch.nn.functional.normalize(torch.randn(n, 3) * 0.2 + torch.tensor([0.0, 0.0, -1.0]), dim=-1)
with torch.no_grad():
    for _ in range(2):
        parts = []
        t0 = time.perf_counter()
        rays = model.space.rays(o, d)
        samples = model.sampler.sample(rays, model.space, model.field, False)
        t1 = time.perf_counter()
        out = model.renderer(model.field, rays, samples, model.space)
        t2 = time.perf_counter()
    print(f"{n} rays: proposal sampling {t1-t0:.2f} s, field + compositing {t2-t1:.2f} s; per 1008x756 frame: {(t1-t0)*762048/n:.0f} s + {(t2-t1)*762048/n:.0f} s")
