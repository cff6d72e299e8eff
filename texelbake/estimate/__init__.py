"""What a bake will cost: the cost model (`costmodel`) and this machine's speed against
the machine its coefficients were fitted on (`machinespeed`)."""
