#!/usr/bin/env python3
"""Distance of a demo's SiLVR cloud to the ground-truth surface, before and after a rigid ICP onto it.

    python3 scripts/surface_offset.py DEMO_OUT      # a `silvr demo` output folder (report.json, dataset/, silvr/)

Maps points.ply and points_filtered.ply into the GT frame with the demo's recorded alignment (when the fields
trained on estimated poses), then prints the mean and median nearest-GT distance (SciPy cKDTree; clouds cropped
to the GT's box), and the same after a rigid ICP of the cloud onto the GT: whether a gap between two runs is the
scoring's alignment or the surfaces themselves (BENCHMARKS.md, pose ablation). Needs numpy and scipy.
"""
import numpy as np, json, sys
from scipy.spatial import cKDTree
def read_ply(p):
    b=open(p,'rb').read(); h=b.index(b'end_header\n')+len(b'end_header\n'); head=b[:h].decode().split('\n')
    n=int([l for l in head if l.startswith('element vertex')][0].split()[2])
    props=[l.split()[1:] for l in head if l.startswith('property')]
    tmap={'double':'<f8','float':'<f4','uchar':'u1','int':'<i4','uint':'<u4'}
    dt=np.dtype([(p[1],tmap[p[0]]) for p in props])
    return np.frombuffer(b[h:h+n*dt.itemsize],dtype=dt)
def quat_to_R(q):
    x,y,z,w=q
    return np.array([[1-2*(y*y+z*z),2*(x*y-z*w),2*(x*z+y*w)],[2*(x*y+z*w),1-2*(x*x+z*z),2*(y*z-x*w)],[2*(x*z-y*w),2*(y*z+x*w),1-2*(x*x+y*y)]])
d=sys.argv[1]
r=json.load(open(d+'/report.json')); a=r['poses'].get('alignment') or r['poses']['refined']['alignment']
trained=r['poses']['trained_on']
gt=read_ply(d+'/dataset/gt/cloud.ply'); G=np.stack([gt['x'],gt['y'],gt['z']],1)
tree=cKDTree(G)
def load(f):
    p=read_ply(d+'/silvr/'+f); P=np.stack([p['x'],p['y'],p['z']],1)
    if trained!='exact':
        P=a['scale']*P@quat_to_R(a['rot']).T+np.array(a['trans'])
    return P
P=load('points.ply'); F=load('points_filtered.ply')
lo,hi=G.min(0),G.max(0)
def acc(X):
    m=np.all((X>=lo)&(X<=hi),1); dd,_=tree.query(X[m]); return dd.mean(), np.median(dd)
print(trained,'camera-Sim3: all',acc(P),'filtered',acc(F))
# ICP (rigid) on points within 10 cm
X=P.copy(); R=np.eye(3); t=np.zeros(3)
for it in range(30):
    dd,idx=tree.query(X); m=dd<0.1
    A=X[m]; B=G[idx[m]]; ca=A.mean(0); cb=B.mean(0)
    U,S,Vt=np.linalg.svd((A-ca).T@(B-cb)); D=np.diag([1,1,np.sign(np.linalg.det(Vt.T@U.T))])
    Ri=Vt.T@D@U.T; ti=cb-Ri@ca; X=X@Ri.T+ti; R=Ri@R; t=Ri@t+ti
ang=np.degrees(np.arccos((np.trace(R)-1)/2)); print('ICP correction: %.3f deg, %.4f m'%(ang,np.linalg.norm(t)))
print(trained,'after ICP: all',acc(P@R.T+t),'filtered',acc(F@R.T+t))
