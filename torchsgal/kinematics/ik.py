class IKResult: pass
def inverse_kinematics(): pass
