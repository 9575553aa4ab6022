# python docs/results/fit_models/droplet_check_at_truth.py VIEW D N  (repository root, PYTHONPATH=.): e.g. droplet_fit_halo 8 8
"""The fit's model check on a droplet view (fitted at 8 x 8), with N pairs of 64-spp renders at diameter D (the
truth's other values): the former ratio (two renders' half-difference scaled by the Gaussian factor) and the
reference-residual ratio that fitting/core.py used then (two renders' mean minus a render at the target's samples per
fit pixel). For a model that explains the target both should read ~1."""
import time, sys, jax, numpy as np, jaxfog
jaxfog.use_cpu_cores()
from fitting.problem import make_view
from fitting.params import apply
TRUTH={"diameter":8.0,"sigma_t":0.3,"albedo":0.9}
name=sys.argv[1]; dval=float(sys.argv[2]); n=int(sys.argv[3])
sf=jaxfog.load_scene(f"data_synthetic/scenes/{name}.json")
t,meta=jaxfog.read_exr(f"data_synthetic/targets/{name}__droplet_8um.exr")
v=make_view(sf.scene,t,name,4,256)
sc=apply(v.scene,{**TRUTH,"diameter":dval}); ref=sc.medium
T=np.asarray(v.target,np.float64)
c0=time.process_time()
cur,new=[],[]
for i in range(n):
    ia=np.asarray(jaxfog.render(sc,jax.random.key(70_000+3*i),64,estimator="proposal",proposal=ref),np.float64)
    ib=np.asarray(jaxfog.render(sc,jax.random.key(70_001+3*i),64,estimator="proposal",proposal=ref),np.float64)
    X=np.asarray(jaxfog.render(sc,jax.random.key(70_002+3*i),256*16,estimator="proposal",proposal=ref),np.float64)
    num=np.median((0.5*(ia+ib)-T)**2)
    cur.append(num/np.median(((ia-ib)/2)**2*(1+2*64/(256*16))))
    new.append(num/np.median((0.5*(ia+ib)-X)**2))
print(f"{name} d={dval}: former ratio {np.round(cur,2)} median {np.median(cur):.2f}; reference-residual ratio {np.round(new,2)} median {np.median(new):.2f}; cpu {time.process_time()-c0:.0f}s")
