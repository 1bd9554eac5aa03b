import json,sys
# Mean recovery per state layer over the 64 field cells: with the partner's whole view, without, constant guess.
out={}
for run in ['a01','a04','a01_u50k']:
    d=json.load(open(f'{run}/recovery.json'))
    by={x['dim']:x for x in d['dims']}
    res={}
    for li,name in enumerate(['agent','food','access']):
        cells=[li*100+r*10+c for r in range(1,9) for c in range(1,9)]
        m=lambda key: sum(sum(by[c][key])/len(by[c][key]) for c in cells)/len(cells)
        res[name]={'with_messages':round(m('with_messages'),4),'without_retrained':round(m('without_retrained'),4),'constant_guess':round(sum(by[c]['constant_guess_rate'] for c in cells)/len(cells),4)}
    out[run+f" (alpha {d['alpha']})"]=res
print(json.dumps(out,indent=1))
