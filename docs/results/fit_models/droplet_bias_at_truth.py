# python docs/results/fit_models/droplet_bias_at_truth.py [VIEW]  (repository root, PYTHONPATH=.): VIEW default droplet_fit_halo
"""At the truth: the fit's model check on the halo view with renders of the truth (is 3.2x a model error or the
check's calibration?), and proposal vs detached vs the target (z-tests)."""
import time, sys, jax, numpy as np, jaxfog
jaxfog.use_cpu_cores()
from fitting.problem import make_view
from fitting.params import apply
TRUTH={"diameter":8.0,"sigma_t":0.3,"albedo":0.9}
name=sys.argv[1] if len(sys.argv)>1 else "droplet_fit_halo"
sf=jaxfog.load_scene(f"data_synthetic/scenes/{name}.json")
t,meta=jaxfog.read_exr(f"data_synthetic/targets/{name}__droplet_8um.exr")
v=make_view(sf.scene,t,name,4,256)
sc=apply(v.scene,TRUTH); ref=sc.medium
T=np.asarray(v.target,np.float64)[...,0]
c0=time.process_time()
for spp in (64,512):
    n=16 if spp==64 else 8
    imgs={e:[] for e in ("proposal","detached")}
    for k in range(n):
        key=jax.random.key(50_000+k)
        imgs["proposal"].append(np.asarray(jaxfog.render(sc,key,spp,estimator="proposal",proposal=ref),np.float64)[...,0])
        imgs["detached"].append(np.asarray(jaxfog.render(sc,jax.random.key(60_000+k),spp,estimator="detached"),np.float64)[...,0])
    P=np.array(imgs["proposal"]); D=np.array(imgs["detached"])
    ratios=[]
    for i in range(0,n,2):
        ia,ib=P[i],P[i+1]
        num=np.median((0.5*(ia+ib)-T)**2); den=np.median(((ia-ib)/2)**2*(1+2*spp/(256*16)))
        ratios.append(num/den)
    print(f"spp {spp}: model check ratio at the truth over {n//2} key pairs: {np.round(ratios,2)} median {np.median(ratios):.2f}")
    for lab,X in (("proposal",P),("detached",D)):
        m=X.mean(0); se=X.std(0,ddof=1)/np.sqrt(n)
        # whole-image mean z vs target (target's SE from the renders' spread scaled to its samples)
        mm=X.mean(axis=(1,2)); se_m=mm.std(ddof=1)/np.sqrt(n)
        se_T=mm.std(ddof=1)*np.sqrt(spp/(256*16))
        print(f"  {lab}: image mean {mm.mean():.4f} +- {se_m:.4f}; target {T.mean():.4f} (+- ~{se_T:.4f}); z {(mm.mean()-T.mean())/np.hypot(se_m,se_T):+.2f};"
              f" per-image means min {mm.min():.3f} max {mm.max():.3f}; median image/mean {np.median(mm)/mm.mean():.3f}")
    mp,md=P.mean(axis=(1,2)),D.mean(axis=(1,2))
    print(f"  proposal - detached: {mp.mean()-md.mean():+.4f}, z {(mp.mean()-md.mean())/np.hypot(mp.std(ddof=1)/np.sqrt(n),md.std(ddof=1)/np.sqrt(n)):+.2f}")
    # per pixel: the median render vs the target, in units of the spread
    print("  per pixel (centre row): target", np.round(T[3],3), "\n   mean proposal", np.round(P.mean(0)[3],3), "\n   median proposal", np.round(np.median(P,0)[3],3))
print("cpu",time.process_time()-c0)
