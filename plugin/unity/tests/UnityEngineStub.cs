// The few UnityEngine types TrackcalTrackedObject.cs uses, so the test compiles and runs it with
// Mono outside Unity. Quaternion * Vector3 is Unity's documented rule (the standard rotation of
// coordinates by a unit quaternion); the rest only stores values.
using System;
using System.Collections.Generic;

namespace UnityEngine
{
    public struct Vector3
    {
        public float x, y, z;
        public Vector3(float x, float y, float z) { this.x = x; this.y = y; this.z = z; }
        public override string ToString() { return "(" + x + ", " + y + ", " + z + ")"; }
    }

    public struct Quaternion
    {
        public float x, y, z, w;
        public Quaternion(float x, float y, float z, float w)
        {
            this.x = x; this.y = y; this.z = z; this.w = w;
        }
        public static Quaternion identity { get { return new Quaternion(0, 0, 0, 1); } }

        public static Vector3 operator *(Quaternion q, Vector3 v)
        {
            // v' = v + 2 w (u x v) + 2 u x (u x v), u = (x, y, z).
            float cx = q.y * v.z - q.z * v.y, cy = q.z * v.x - q.x * v.z, cz = q.x * v.y - q.y * v.x;
            float dx = q.y * cz - q.z * cy, dy = q.z * cx - q.x * cz, dz = q.x * cy - q.y * cx;
            return new Vector3(v.x + 2 * (q.w * cx + dx), v.y + 2 * (q.w * cy + dy),
                               v.z + 2 * (q.w * cz + dz));
        }
    }

    public class Transform
    {
        public Vector3 localPosition;
        public Quaternion localRotation = Quaternion.identity;
    }

    public class Object
    {
        public string name = "stub";
    }

    public class Component : Object
    {
        private readonly Transform t = new Transform();
        public Transform transform { get { return t; } }
    }

    public class Behaviour : Component
    {
        public bool enabled = true;
    }

    public class MonoBehaviour : Behaviour
    {
    }

    public static class Debug
    {
        public static readonly List<string> Errors = new List<string>();
        public static void LogError(object message) { Errors.Add(message.ToString()); }
    }

    [AttributeUsage(AttributeTargets.Field)]
    public class TooltipAttribute : Attribute
    {
        public TooltipAttribute(string tooltip) { }
    }
}
