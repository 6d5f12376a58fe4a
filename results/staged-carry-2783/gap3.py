import sys
def parse(tok):
    p,f=tok.split(':'); return int(p),float(f)
win3=[];top3=[];win2=[];cnt={};cnt2={};n=0;carried=[]
M=[10,15,20,25,30,40,50]
for line in open(sys.argv[1]):
    t=line.split(); i=t.index('S'); r=t.index('R')
    C=dict(parse(x) for x in t[1:i]); S=[parse(x) for x in t[i+1:r]]; R=[parse(x) for x in t[r+1:]]
    if not C or not R: continue
    n+=1; carried.append(len(C))
    m3=min(C.values()); w=R[0][0]
    win3.append(C[w]-m3); top3.append(max(C[p]-m3 for p,_ in S))
    m2=min(f for _,f in S); s2=dict(S); win2.append(s2[w]-m2)
    for mm in M:
        cnt.setdefault(mm,0); cnt[mm]+=max(8,sum(1 for v in C.values() if v<=m3+mm))
        cnt2.setdefault(mm,0); cnt2[mm]+=sum(1 for v in s2.values() if v<=m2+mm)
def q(a):
    a=sorted(a); return ' / '.join('%.1f'%a[min(len(a)-1,int(p*len(a)))] for p in (0.5,0.9,0.95,0.99)) + ' / %.1f'%a[-1]
print('events',n,'carried mean %.1f'%(sum(carried)/n))
print('level-3 gap of the winner 50/90/95/99/max:',q(win3))
print('level-3 gap of the select top-8 (max):',q(top3))
for mm in M: print(' margin %d: winners missed %d, top-8 broken %d, carried to level 2 %.1f'%(mm,sum(1 for g in win3 if g>mm),sum(1 for g in top3 if g>mm),cnt[mm]/n))
print('select-level gap of the winner:',q(win2))
for mm in M: print(' rank margin %d: winners missed %d, candidates ranked %.2f'%(mm,sum(1 for g in win2 if g>mm),cnt2[mm]/n))
